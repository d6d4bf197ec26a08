"""The scene-graph model, shared by its producer (fusion) and its readers (query, viewer).

- :mod:`shared.graph.scene`: the versioned :class:`SceneGraph` that emits deltas, and the
  :class:`GraphReplica` that applies them;
- :mod:`shared.graph.sync`: keeping a replica in step from deltas and snapshots;
- :mod:`shared.graph.store`: atomic, checksummed snapshots on disk;
- :mod:`shared.graph.dsg`: the Hydra / spark_dsg writer and reader.

Nothing here imports zenoh or any service.
"""
