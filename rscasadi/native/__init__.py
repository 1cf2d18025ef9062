"""Compiling generated C, caching it by hash, loading it, and running it in parallel."""
