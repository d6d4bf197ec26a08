"""The query service: eq. 10 retrieval over a replica of the live graph, a Python client and offline queries on a saved map."""

from shared.registry import SERVICES, ServiceEntry

SERVICES.register(
    "query",
    ServiceEntry("eq. 10 retrieval over a replica of the live graph", node="services.query.node:build"),
)
