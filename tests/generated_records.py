"""One tiny generated dataset and its records, for the tests that turn them into SuctionNet trees."""

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
