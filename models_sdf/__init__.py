"""Robot models, installed as the package `ditch_drake.models_sdf` (see package.xml)."""
