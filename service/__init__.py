"""The AGG HTTP service: FastAPI app, job store, uploads, auth and ``agg serve``."""
