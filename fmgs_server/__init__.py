"""gRPC query server over the fmgs core library (scene repository in ``models/``)."""

__version__ = "0.1.0"
