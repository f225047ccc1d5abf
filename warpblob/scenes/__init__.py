"""Reference models (filled in below)."""
