"""Curation of generated datasets: review GUI, automatic pre-flags, versioned manifests."""
