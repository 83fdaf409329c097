"""Job runner (RQ worker) and the gRPC servers of the AGG service."""
