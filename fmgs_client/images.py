"""Moved: the image encodings live in fmgs_wire.images (shared with the server)."""

from fmgs_wire.images import *  # noqa: F403
