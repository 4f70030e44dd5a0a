"""The wire contract ``fmgs.v1``, shared by the server and the client: generated protobuf and gRPC modules
(``fmgs_wire.proto.fmgs.v1``), the tensor codec (``fmgs_wire.tensors``) and the image encodings with their
scale constants (``fmgs_wire.images``). Needs only protobuf, grpcio and numpy: never torch.
"""

__version__ = "0.1.0"

DEFAULT_PORT = 50051
"""The port a server binds and a client dials when told none (fmgs-server --port, fmgs-client --address)."""
