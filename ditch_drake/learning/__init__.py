"""Behavioural cloning (paper 3.4-3.6): the network, the data, SMOTE, metrics, training, checkpoints."""
