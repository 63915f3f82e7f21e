"""The label sets a dataset can store, in a module of their own so that readers of datasets (the trainer, the
dataset config) name them without importing the scorer, pybullet and Open3D (parcelpick_env/suction/quality.py
makes the labels; docs/labels.md, "Label sets")."""

LABEL_SETS: tuple[str, ...] = ("paper", "physical", "suctionnet")  # what dataset.generate --labels offers
