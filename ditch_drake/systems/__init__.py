"""The project's LeafSystems, one per file."""
