"""Packaged data: the environments file."""
