"""Named definitions of a good suction, for labels and for the offline AP, all computed by ``SuctionScorer``.

docs/labels.md ("Label sets") and docs/protocols.md ("Quality definitions") give the sources. In short:

============== ========================================================================================
``paper``       The paper's labels: spring seal, the corrected wrench (norm torque about the COM times the
                gravity-angle factor), collision on parcels, bin and floor; 10 mm cup, unit mass.
``suctionnet``  SuctionNet-1Billion's evaluator: its seal (72 bins over r +- 1 mm, highest point, fit x
                deform), its wrench (larger bending component about the surface centroid, no angle factor),
                collision on the objects and the table (the tote floor) only; 10 mm cup, unit mass.
``physical``    Would the pick hold in this env (``suction/physical.py``): the env's 40 mm bellows cup
                seated on the hull, real masses and COMs, Dex-Net's ring conditions hanging still, the
                physical tool and wrist against hulls, bin and floor.
``paper_compat`` SuctionNet's seal with its lenient label-time wrench, for the AP's paper-compatible row
                (eval/ap.py also turns NMS off there, as the public Diffusion_Suction test script does).
============== ========================================================================================

Each definition gives the four channels (seal, wrench, collision, visibility); its quality is the product of
the first three, and ``total`` multiplies in visibility.
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Literal

import numpy as np

from parcelpick_env.suction.config import SuctionConfig
from parcelpick_env.suction.cup import CupSpec
from parcelpick_env.suction.scorer import SuctionScorer, SuctionScores

if TYPE_CHECKING:
    from parcelpick_env.envs.config import EnvConfig
    from parcelpick_env.scene.scene import Scene

Definition = Literal["paper", "suctionnet", "physical", "paper_compat"]
DEFINITIONS: tuple[str, ...] = ("paper", "suctionnet", "physical", "paper_compat")
AP_DEFINITIONS: tuple[str, ...] = ("suctionnet", "physical", "paper_compat")  # what eval/ap.py --quality offers

# SuctionNet's evaluator constants (suctionnetAPI utils/eval_utils.py): r = 10 mm, k = 15.6, g = 9.8, unit mass,
# a 10 mm tool from 10 to 100 mm along n. They are SuctionConfig's defaults; only the models differ.
SUCTIONNET_EVALUATOR = SuctionConfig(seal_model="suctionnet", wrench_model="suctionnet")
SUCTIONNET_LABEL_TIME = SuctionConfig(seal_model="suctionnet", wrench_model="suctionnet_label")
PAPER_LABELS = SuctionConfig()  # spring seal, paper wrench


@functools.cache
def _env_config() -> "EnvConfig":
    """The env's default config (frozen), built once; imported late because the envs package imports suction."""
    from parcelpick_env.envs.config import EnvConfig

    return EnvConfig()


@dataclass(frozen=True)
class PhysicalCell:
    """The env's cup as the ``physical`` definition sees it; defaults are ``EnvConfig()``'s."""

    suction: SuctionConfig = field(default_factory=lambda: _env_config().suction)
    cup: CupSpec = field(default_factory=lambda: _env_config().grasp.cup)
    seal_threshold: float = field(default_factory=lambda: float(_env_config().grasp.seal_threshold))

    def __post_init__(self) -> None:
        if self.suction.seal_model != "bellows":
            object.__setattr__(self, "suction", dataclasses.replace(self.suction, seal_model="bellows"))
        if not 0.0 <= self.seal_threshold <= 1.0:
            raise ValueError(f"PhysicalCell.seal_threshold must be in [0, 1], got {self.seal_threshold!r}")


def check_definition(name: str, allowed: tuple[str, ...] = DEFINITIONS, what: str = "quality definition") -> str:
    if name not in allowed:
        raise ValueError(f"unknown {what} {name!r}; choose one of {', '.join(allowed)}")
    return name


def definition_config(name: str, cell: PhysicalCell | None = None) -> SuctionConfig:
    """The scorer config a definition uses."""
    check_definition(name)
    if name == "physical":
        return (cell or PhysicalCell()).suction
    return {"paper": PAPER_LABELS, "suctionnet": SUCTIONNET_EVALUATOR, "paper_compat": SUCTIONNET_LABEL_TIME}[name]


def definition_scorer(name: str, scene: "Scene", cell: PhysicalCell | None = None,
                      num_threads: int | None = None) -> SuctionScorer:
    """The one scorer, configured for definition ``name`` on a scene's true meshes. SuctionNet's evaluator
    blocks the tool on the objects and the table (the tote floor), not on the bin walls."""
    config = definition_config(name, cell)
    if num_threads is not None:
        config = dataclasses.replace(config, num_threads=num_threads)
    obstacles = scene.bin.floor_meshes() if name in ("suctionnet", "paper_compat") else None
    return SuctionScorer.from_scene(scene, config, obstacles=obstacles)


def score_definition(name: str, scorer: SuctionScorer, points: np.ndarray, normals: np.ndarray,
                     object_ids: np.ndarray, visibility: np.ndarray | None = None,
                     cell: PhysicalCell | None = None) -> SuctionScores:
    """The four channels of definition ``name`` for candidates ``(p, n)`` on ``object_ids`` (``scorer`` from
    ``definition_scorer``); ``visibility`` is per object, None means 1."""
    check_definition(name)
    if name != "physical":
        return scorer.score(points, normals, object_ids, visibility=visibility)
    cell = cell or PhysicalCell()
    grasp = scorer.physical(points, normals, object_ids, cup=cell.cup)
    seal, wrench, collision = grasp.channels(cell.seal_threshold)
    vis = scorer.candidate_visibility(object_ids, visibility)
    return SuctionScores(seal=seal, wrench=wrench, collision=collision, visibility=vis,
                         total=(seal * wrench * collision * vis).astype(np.float32))
