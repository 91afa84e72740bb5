"""Zenoh adapters: the only package that imports zenoh."""
