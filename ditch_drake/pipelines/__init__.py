"""Training pipelines: the paper's protocol from an experiment file (`experiment.py`) and the
generalist's recipe over the procedural benchmark (`generalist.py`), built on shared stages."""
