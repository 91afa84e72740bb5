"""The wire: every word, key and payload of the contract (docs/contract.md), defined once.

* :mod:`.vocabulary`: source ids, correlation method names, rejection reasons;
* :mod:`.models`: the pydantic models of every payload, in and out (their JSON Schemas are
  committed in ``schemas/``), and the mapping of validation errors to rejection reasons;
* :mod:`.keys`: the key grammar, built and parsed in one place for the service and recorder;
* :mod:`.outputs`: fast builders of the output payloads' JSON, validated against the models
  by the tests.

Nothing here imports the numerics, the transport or the web framework.
"""
