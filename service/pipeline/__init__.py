"""The engine's stages: stateful, push-style, no I/O and no threads.

An input message goes ``decode -> sequencer -> tracking -> correlation -> read model``:

* :mod:`.sequencer` owns every source's ``seq`` and data clock, the hostile-input policies on
  them, and the release of accepted batches in data-time order (the watermark);
* :mod:`.tracking_stage` owns the radars' sites and trackers, one update per released batch;
* :mod:`.correlation_stage` owns the pair correlators, their cadence and the joint bias solve;
* :mod:`.read_model` owns what readers see: immutable snapshots whose outputs are built only
  when first read.

:class:`service.engine.Engine` is the thin coordinator that strings them together.
"""
