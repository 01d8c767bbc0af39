"""The simulated world and the task. Registers the gymnasium id ``ShieldNav-v0``.

``gymnasium.make("ShieldNav-v0")`` gives one vehicle (:class:`envs.navigation.ShieldNavEnv`);
``gymnasium.make_vec("ShieldNav-v0", num_envs=N)`` gives the natively batched
:class:`envs.navigation.NavigationEnv`. Keyword arguments are dotted config overrides.
"""

import gymnasium

if "ShieldNav-v0" not in gymnasium.registry:
    gymnasium.register(
        id="ShieldNav-v0",
        entry_point="envs.navigation:ShieldNavEnv",
        vector_entry_point="envs.navigation:NavigationEnv",
        disable_env_checker=True,
    )
