"""Learning algorithms, and the controllers they learn from or are measured against.

PPO near a start actor (:mod:`.anchored`), DAgger distillation (:mod:`.distillation`), the privileged planning expert
(:mod:`.expert`, :mod:`.mppi`), velocity tracking (:mod:`.tracking`) and the weight-free baselines (:mod:`.baselines`).
"""

ANCHOR_TARGETS = ("actor_init", "expert")
"""What :class:`~shield_nav.algorithms.anchored.AnchoredPPO` holds the actor near: its own starting weights, or the
scripted expert's action (observation ``expert``). Here rather than in :mod:`.anchored`, so that checking a training
config does not import torch."""
