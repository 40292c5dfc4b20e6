"""Demonstrations: the on-disk format and collection."""
