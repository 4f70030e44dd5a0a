"""Scene packages: export and validated loading of what serving needs."""
