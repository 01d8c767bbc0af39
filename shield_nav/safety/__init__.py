"""The safety layer.

The HOCBF shield (:mod:`.shield`), its barrier rows and kernels (:mod:`.rows`), and the stall escape with the map of
what a flight's camera has shown (:mod:`.escape`).
"""
