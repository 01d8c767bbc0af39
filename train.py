"""Train the depth CNN+GRU policy with rsl-rl PPO: ``python train.py --config configs/train/<name>.yaml [...]``.

See ``python train.py --help`` and docs/training.md. The logic lives in :mod:`shield_nav.training`.
"""

from shield_nav.openmp import limit_spinning

limit_spinning()  # before torch and numba load libgomp (shield_nav/openmp.py)

from shield_nav.training.cli import main  # noqa: E402

if __name__ == "__main__":
    raise SystemExit(main())
