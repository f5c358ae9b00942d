"""Synthetic multiview head datasets: cameras, the volume renderer, generators and shards."""
__version__ = "0.1.0"
