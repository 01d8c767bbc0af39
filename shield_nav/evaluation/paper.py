"""The paper's Tables I and II, as numbers, so figures and checks can set our rows beside them.

Quoted from *High-Speed Vision-Based Flight in Clutter with Safety-Shielded Reinforcement Learning* (Zhang, Lei et
al.; ``../shared/paper/``): Table I, "Results of Ablation Study Across Target Speeds" (8 unseen ablation scenes x 50
trials per speed), success rate % and average velocity of the successful flights (m/s); Table II, "Benchmark
Comparison of Success Rates Across Target Speed" (16 unseen benchmark scenes, 160 trials per speed), success rate %.
The paper reports no interval. ``None`` marks a cell the paper leaves empty (Distance at 9 m/s has no successful
flight, so no velocity).

Keys are this repository's ``eval.py`` row names where a row reproduces the paper's (``distance``, ``dijkstra``,
``dijkstra_cbf``, ``full``); the paper's other methods in Table II, which are not reimplemented here, keep their own
names. ``docs/results.md`` quotes the same numbers in italics, and a test checks that the two agree.
"""

from __future__ import annotations

__all__ = ["PAPER_SPEEDS", "PAPER_TABLE_I", "PAPER_TABLE_II"]

#: Target speeds (m/s) of both tables' columns.
PAPER_SPEEDS: tuple[float, ...] = (3.0, 5.0, 7.0, 9.0)

#: Table I: row -> label, success rate % and mean realised velocity (m/s) per target speed.
PAPER_TABLE_I: dict[str, dict] = {
    "distance": {"label": "Distance", "sr": (51.75, 35.00, 21.25, 0.0), "vel": (3.04, 5.16, 7.11, None)},
    "dijkstra": {"label": "Dijkstra", "sr": (62.25, 67.75, 56.25, 43.75), "vel": (3.02, 5.18, 6.76, 8.36)},
    "dijkstra_cbf": {"label": "Dijkstra + CBF", "sr": (84.50, 94.00, 52.25, 37.25), "vel": (3.03, 4.99, 6.99, 8.70)},
    "full": {"label": "Full", "sr": (88.75, 100.0, 75.00, 47.50), "vel": (3.00, 4.90, 6.79, 9.00)},
}

#: Table II: method -> label and success rate % per target speed. The table has no velocity column; for its own method
#: the text of the benchmark section gives the mean successful speed at the two ends, 3.00 m/s at 3 and 7.58 at 9.
PAPER_TABLE_II: dict[str, dict] = {
    "ego_planner": {"label": "Ego-Planner", "sr": (70.62, 0.62, 0.00, 0.00)},
    "navrl": {"label": "NavRL", "sr": (43.12, 5.00, 3.12, 0.00)},
    "yopo": {"label": "YOPO", "sr": (26.88, 21.25, 10.62, 6.88)},
    "diffphys": {"label": "DiffPhys", "sr": (70.62, 55.62, 57.50, 51.25)},
    "full": {"label": "Ours (Full)", "sr": (96.88, 96.25, 73.75, 56.88), "vel": (3.00, None, None, 7.58)},
}
