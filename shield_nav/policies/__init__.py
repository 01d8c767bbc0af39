"""The policies.

The CNN + GRU actor for rsl-rl and its exports (:mod:`.models`), and ensembles of actors exported as one policy
(:mod:`.ensemble`).
"""
