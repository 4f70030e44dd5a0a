"""The feature field: hash encoding at the Gaussian means, language and DINO heads, Gaussian selection."""
