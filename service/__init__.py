"""The maxfs-ps service: HTTP API, Dask orchestration, CLI and client."""
