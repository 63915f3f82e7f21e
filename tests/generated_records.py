"""Tiny generated datasets: their records, for the tests that turn them into SuctionNet trees, and the smallest
dataset a policy's evaluation reads."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from dataset.config import GenerationConfig
from dataset.generate import generate
from dataset.storage import open_dataset


def generate_records(out: Path, **config: Any) -> list[dict[str, Any]]:
    """Generate ``GenerationConfig(**config)`` into ``out`` (one process, no progress bar) and read back every record."""
    generate(out, GenerationConfig(**config), workers=1, progress=False)
    store = open_dataset(out)
    try:
        return [store.scene(i) for i in range(len(store))]
    finally:
        store.close()


TINY = dict(scenes=2, min_parcels=3, max_parcels=3, width=160, height=120, annotation_points=512, scenes_per_shard=2)


def generate_tiny(out: Path, **config: Any) -> Path:
    """Two scenes of three parcels at 160 x 120 (``TINY``, ``config`` overriding it) into ``out``, one process, no
    progress bar; returns ``out``."""
    generate(out, GenerationConfig(**{**TINY, **config}), workers=1, progress=False)
    return out
