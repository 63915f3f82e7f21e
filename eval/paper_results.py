"""The paper's own numbers (docs/protocols.md), kept apart so reports can put ours beside them."""

from __future__ import annotations

from dataset.suctionnet.layout import CAMERAS, TEST_SPLITS  # (kinect, realsense); seen, similar, novel

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
    "diffusion": "Diffusion-Suction", "diffusion_vote": "Diffusion-Suction + centre votes",
    "diffusion_hold": "Diffusion-Suction + hold check",
    "diffusion_vote_hold": "Diffusion-Suction + centre votes + hold check", "cao": "Cao et al.", "normal_std": "Normal-STD",
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

# Table I, SuctionNet-1Billion: per Top-k and method, the paper's cells per split as (AP, AP0.8, AP0.4), each
# "Kinect/RealSense" as the paper prints them. TABLE_I expands it to (camera, split, top, method) -> the 3 values.
_TABLE_I_PRINTED: dict[tuple[str, str], str] = {
    ("Top-50", "normal_std"): "6.16/10.10 0.74/1.01 7.20/12.64 17.54/19.23 2.38/2.26 24.68/25.95 1.34/3.50 0.12/0.23 1.08/4.22",
    ("Top-50", "dexnet"): "9.46/15.50 0.96/1.53 11.90/20.22 14.93/18.92 2.45/2.62 19.05/24.51 1.68/2.62 0.04/0.35 1.89/5.32",
    ("Top-50", "cao"): "15.94/28.31 1.25/3.41 20.89/38.56 18.06/26.64 1.96/3.42 24.00/35.34 3.20/8.23 0.25/0.35 3.78/10.29",
    ("Top-50", "diffusion"): "22.03/31.90 3.25/4.79 30.13/42.78 19.17/31.59 2.62/4.27 25.56/41.38 4.64/10.00 0.50/0.76 5.73/12.32",
    ("Top-1", "normal_std"): "11.68/15.40 1.94/1.82 13.35/18.83 34.11/31.20 6.51/4.74 47.28/43.46 2.64/4.89 0.28/0.52 3.72/5.96",
    ("Top-1", "dexnet"): "12.30/10.61 3.36/1.30 15.03/13.91 20.75/14.28 5.39/2.40 26.00/17.71 1.09/2.81 0.08/0.29 1.17/3.15",
    ("Top-1", "cao"): "26.44/43.98 2.90/7.79 35.98/60.81 24.59/36.59 2.45/6.54 32.89/49.30 6.66/14.32 0.13/0.38 8.80/19.95",
    ("Top-1", "diffusion"): "35.97/54.79 13.68/21.03 47.55/68.59 19.31/47.00 5.18/16.08 25.36/59.36 7.49/14.14 2.88/2.42 8.46/17.67",
}


def _expand_table_i() -> dict[tuple[str, str, str, str], tuple[float, float, float]]:
    table: dict[tuple[str, str, str, str], tuple[float, float, float]] = {}
    for (top, method), printed in _TABLE_I_PRINTED.items():
        cells = [[float(v) for v in cell.split("/")] for cell in printed.split()]  # 3 splits x 3 columns
        for c, camera in enumerate(CAMERAS):
            for s, split in enumerate(TEST_SPLITS):
                ap, ap08, ap04 = (cells[3 * s + k][c] for k in range(3))
                table[(camera, split, top, method)] = (ap, ap08, ap04)
    return table


TABLE_I: dict[tuple[str, str, str, str], tuple[float, float, float]] = _expand_table_i()
