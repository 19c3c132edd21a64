"""The API's routers, one per concern: localisation, the index, health and metrics."""
