"""File formats: graphdeco PLY, safetensors, atomic writes."""
