"""Diagram builders: plain functions from config dataclasses."""
