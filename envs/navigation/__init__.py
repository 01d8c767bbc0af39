"""The navigation task ``ShieldNav-v0``: batched VectorEnv, single-env wrapper, config and reward terms."""

from envs.navigation.config import REWARD_TERMS, NavConfig
from envs.navigation.env import PRIV_EXTRA, STATE_DIM, STATE_LAYOUT, NavigationEnv
from envs.navigation.single import ShieldNavEnv

__all__ = ["PRIV_EXTRA", "REWARD_TERMS", "STATE_DIM", "STATE_LAYOUT", "NavConfig", "NavigationEnv", "ShieldNavEnv"]
