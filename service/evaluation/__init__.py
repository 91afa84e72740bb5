"""Evaluation code the runtime carries: the simulator's ``truth_id`` of each track.

The contract passes ``truth_id`` through (``TrackBatch.truth_id``: the most common label of a
track's plots) so that a client can score the outputs of simulated input.  No algorithm reads
it: the numerics never import this package (an import rule in ``pyproject.toml``).
"""
