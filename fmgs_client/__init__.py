"""Thin client for the FMGS query server: grpcio, protobuf and numpy only (no torch)."""

__version__ = "0.1.0"
