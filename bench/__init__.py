"""Benchmarks of mi-lidar (``make bench`` runs ``python -m bench``)."""
