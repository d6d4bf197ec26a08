"""The query service: eq. 10 retrieval over a replica of the live graph, a Python client and offline queries on a saved map."""
