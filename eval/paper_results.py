"""The paper's own numbers (docs/protocols.md), kept apart so reports can put ours beside them."""

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
    "oracle": "Oracle (privileged ceiling)",
    "diffusion": "Diffusion-Suction", "cao": "Cao et al.", "normal_std": "Normal-STD",
    "dexnet": "Dex-Net 3.0", "random": "Random", "sb3": "PPO (SB3)",
}

# Table II, Top-1: AP / AP0.8 / AP0.4 (k = 1 only).
TABLE_II_TOP1: dict[str, tuple[float, float, float]] = {
    "diffusion": (98.00, 92.00, 100.00),
    "cao": (66.25, 30.00, 82.00),
    "normal_std": (55.75, 2.00, 84.00),
    "dexnet": (6.50, 0.00, 4.00),
}

# Table III, framework ablations (Top-50 AP / AP0.8 / AP0.4); keys name our trained variants.
TABLE_III_ABLATION: dict[str, tuple[float, float, float]] = {
    "no_normals": (93.09, 81.06, 97.23),
    "no_visibility": (89.15, 72.08, 95.59),
    "pointnet": (38.39, 8.72, 48.67),
    "dgcnn": (78.41, 39.56, 93.76),
    "full": (94.42, 85.04, 97.65),
}

# Table IV, denoising steps: (training steps, inference steps) -> (AP, AP0.8, AP0.4, time in ms on the paper's GPU).
TABLE_IV_STEPS: dict[tuple[int, int], tuple[float, float, float, float]] = {
    (5, 5): (94.17, 84.00, 97.61, 181), (10, 10): (94.23, 84.12, 97.63, 185), (15, 15): (93.57, 82.36, 97.36, 194),
    (20, 5): (28.10, 22.99, 29.86, 181), (20, 10): (81.95, 48.54, 95.03, 188), (20, 15): (10.06, 9.73, 10.15, 193),
    (20, 20): (94.42, 85.04, 97.65, 204),
}
