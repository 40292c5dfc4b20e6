"""ditch_drake: negative-obstacle traversal by behavioural cloning, built on Drake."""

__version__ = "0.1.0"
