"""TopoFusion lab: the simulator, its scenarios and Zenoh publisher, and the evaluation studies.

Not part of the runtime distribution: the service never imports it; only the ``demo``,
``simulate`` and ``evaluate`` commands of ``topofusion`` do, lazily.
"""
