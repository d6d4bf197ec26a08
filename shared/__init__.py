"""TrackGraph's common library: configs, message contracts, codec, topics, transport, geometry.

Nothing here imports torch, and only :mod:`shared.transport` imports zenoh.
"""

SCHEMA_VERSION = 2
"""Wire schema version carried by every envelope; bumped on incompatible message changes
(2: ground truth left the wire, no message has an ``instances`` field)."""
