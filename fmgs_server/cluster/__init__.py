"""Serving on a Ray cluster: the same ``fmgs.v1.Fmgs`` service through Ray Serve's gRPC proxy.

Nothing here imports Ray until a deployment is built (``fmgs_server.cluster.app``), so the base server
works without the ``fmgs[ray]`` extra.
"""
