"""compare_runs: tensorboard scalars -> CSV -> overlay figure, on real event files."""

from torch.utils.tensorboard import SummaryWriter

from shield_nav.tools.compare_runs import compare, read_csv, read_events, smooth, write_csv


def _fake_run(path, success):
    w = SummaryWriter(log_dir=str(path))
    for it, s in enumerate(success):
        w.add_scalar("episode/success", s, it)
        w.add_scalar("Train/mean_reward", 10 * s, it)
    w.close()


def test_events_csv_round_trip_and_compare(tmp_path):
    ref_run, my_run = tmp_path / "ref_run", tmp_path / "mine"
    _fake_run(ref_run, [0.0, 0.25, 0.5, 0.75])
    _fake_run(my_run, [0.0, 0.5, 1.0])
    series = read_events(str(ref_run))
    assert series["episode/success"] == [(0, 0.0), (1, 0.25), (2, 0.5), (3, 0.75)]
    ref_dir = tmp_path / "checkpoint"
    ref_dir.mkdir()
    write_csv(series, str(ref_dir / "curves.csv"))
    assert read_csv(str(ref_dir / "curves.csv")) == series
    rows = compare(str(my_run), [str(ref_dir)], str(tmp_path / "cmp.png"))
    assert (tmp_path / "cmp.png").stat().st_size > 1000
    row = next(r for r in rows if r["tag"] == "episode/success")
    # Last shared iteration is 2; the mean over iterations (-18, 2] is (0 + 0.25 + 0.5) / 3 for the reference and
    # (0 + 0.5 + 1) / 3 for the run.
    assert row["iteration"] == 2
    assert abs(row["checkpoint"] - 0.25) < 1e-6 and abs(row["mine"] - 0.5) < 1e-6


def test_smooth_is_a_trailing_mean():
    assert smooth([1.0, 3.0, 5.0, 7.0], window=2) == [1.0, 2.0, 4.0, 6.0]
