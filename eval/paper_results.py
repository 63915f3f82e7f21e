"""The paper's own numbers (DESIGN.md), kept apart so reports can put ours beside them."""

from __future__ import annotations

# Table II, Top-50: AP / AP0.8 / AP0.4 on the Parcel-Suction-Dataset test split.
TABLE_II_TOP50: dict[str, tuple[float, float, float]] = {
    "diffusion": (94.42, 85.04, 97.65),
    "cao": (62.81, 28.29, 78.66),
    "normal_std": (50.98, 6.09, 73.16),
    "dexnet": (9.56, 0.46, 9.47),
}

# Table V, real-robot Diffusion-Suction: (R_grasp, R_object) in percent.
TABLE_V: dict[tuple[str, str], tuple[float, float]] = {
    ("rectangular", "scattered"): (96.43, 100.0), ("rectangular", "stacked"): (93.75, 100.0),
    ("planar", "scattered"): (100.0, 100.0), ("planar", "stacked"): (94.64, 100.0),
    ("cylindrical", "scattered"): (81.36, 90.83), ("cylindrical", "stacked"): (78.69, 100.0),
    ("mixed", "scattered"): (94.44, 97.62), ("mixed", "stacked"): (93.33, 100.0),
}

METHOD_LABELS: dict[str, str] = {
    "diffusion": "Diffusion-Suction", "cao": "Cao et al.", "normal_std": "Normal-STD",
    "dexnet": "Dex-Net 3.0", "random": "Random", "sb3": "PPO (SB3)",
}
