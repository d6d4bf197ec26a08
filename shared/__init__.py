"""TrackGraph's common library: configs, message contracts, codec, topics, transport, geometry.

Nothing here imports torch, and only :mod:`shared.transport` imports zenoh.
"""

SCHEMA_VERSION = 1
"""Wire schema version carried by every envelope; bumped on incompatible message changes."""
