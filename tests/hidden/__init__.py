"""Hidden-effect test sets written by independent numpy simulators (not the project's sampler)."""
