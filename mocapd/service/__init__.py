"""Configuration, the asyncio application, HTTP status/metrics and the command line."""
