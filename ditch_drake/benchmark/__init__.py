"""The procedural ditch benchmark: seeded ditches in named splits, and their evaluation."""
