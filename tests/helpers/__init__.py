"""Shared test helpers: reference renderer, scenes, tolerances, fakes of the wire and the service."""
