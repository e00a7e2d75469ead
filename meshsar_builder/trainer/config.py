"""Trainer configs (manifests/train/*.toml): `meshsar train CONFIG ...`.

A config has top-level `name` and `seed` and the tables [data], [model]
(model.ModelConfig), [loss], [radar_loss], [optim], [run] and [refine]; unknown keys and
wrong types are errors naming the file and the key.
"""

from __future__ import annotations

import dataclasses
import os
import re
from dataclasses import dataclass, field

from meshsar_builder.pipeline.errors import InputError, RecipeError
from meshsar_builder.pipeline.recipe import build, parse_toml, read_text
from meshsar_builder.trainer import losses as L
from meshsar_builder.trainer.model import ModelConfig

RADAR_BALANCES = ("gradient", "none")
RADAR_TARGETS = ("clean", "recorded")
LR_SCHEDULES = ("constant", "cosine")


@dataclass(frozen=True)
class DataConfig:
    """[data]: what the model sees."""

    channels: tuple[str, ...] = ("intensity", "depth")  # sar channels, by name
    views: tuple[str, ...] = ()  # view names to use; empty: all (["anterior"]: the one-view ablation)
    batch_size: int = 1
    workers: int = 0  # DataLoader worker processes per rank
    val_fraction: float = 0.1  # of the train split, held out for validation (grouped by subject); 0: none

    def __post_init__(self):
        if not self.channels:
            raise ValueError("channels: need at least one channel")
        if self.batch_size < 1 or self.workers < 0:
            raise ValueError(f"batch_size/workers: need >= 1 / >= 0, got {self.batch_size}, {self.workers}")
        if not 0 <= self.val_fraction < 1:
            raise ValueError(f"val_fraction: need 0 <= val_fraction < 1, got {self.val_fraction}")


@dataclass(frozen=True)
class LossConfig:
    """[loss]: weights of Chamfer, Laplacian, edge length, normal consistency (summed over stages)."""

    weights: tuple[float, float, float, float] = (0.3, 0.05, 0.46, 0.16)
    chamfer_points: int = 4000  # points sampled on the ground-truth surface per sample and step

    def __post_init__(self):
        if min(self.weights) < 0 or self.chamfer_points < 1:
            raise ValueError(f"weights/chamfer_points: need >= 0 / >= 1, got {list(self.weights)}, {self.chamfer_points}")


@dataclass(frozen=True)
class RadarLossConfig:
    """[radar_loss]: the radar term (DESIGN section 10; docs/trainer.md "The radar loss").

    mode "focused": 1 - cosine of blurred, debiased power volumes, the target
    focused from the loss-grid echo (echo_clean, or the recorded noisy echo) and the
    prediction from an image-domain splat of the predicted mesh (radar/focused.py).
    "depth" (default.toml's): the same volumes compared by their depth maps (focused.depth_distance, in mm).
    "raw" (the paper's) and "profile": the relative L1 between the differentiable echo and the target's
    echo on the loss grid (DatasetGeometry.echo_targets).
    """

    weight: float = 0.1  # 0: the no-radar-loss ablation
    warmup_epochs: int = 20  # the weight is 0 before this epoch
    ramp_epochs: int = 0  # then rises linearly to `weight` over this many epochs (0: at once)
    # gradient: the radar term's gradient on the compared mesh is rescaled, per step, to `weight`
    # times the norm of the geometric terms' gradient there; its logged value is rescaled alike
    # (radar_l1 logs the plain relative L1). The echo's phase makes the plain term's vertex
    # gradients ~200x the geometric ones (measured on the demo set: 2e-2 vs 8e-5 per vertex at
    # weight 0.1), so without this any useful weight swamps Chamfer. none: weight x relative L1.
    balance: str = "gradient"
    # profile: |IFFT over frequency|; raw: the complex signal (paper). Measured on a 2,562-vertex
    # ellipsoid against its Embree echo: raw jumps 0.65 -> 1.95 within 1 mm (phase wraps), profile
    # varies smoothly with its minimum within 2 mm and a basin of about -8..+4 mm.
    mode: str = "profile"
    beta: float = 10.0  # steepness of the soft visibility (raw, profile)
    # the target's echo, "clean" (echo_clean) or "recorded" (echo_clean plus the build's noise regenerated
    # from noise_seed; focused and depth subtract its expected image power)
    target: str = "clean"
    focused_lateral_mm: float = 2.5  # voxel size across the view
    focused_range_mm: float = 5.0  # voxel size along the view
    focused_blur_mm: float = 3.0  # Gaussian blur of both volumes
    # focused and depth modes: heat-kernel steps applied to its per-vertex gradient (0: none): the raw
    # gradient is high-frequency (cosine to the true direction <= 0.03, issue 28)
    smooth_iterations: int = 0
    antennas: int = 0  # raw, profile: antennas per view drawn each step (0: every antenna of the loss grid)
    stage: int = -1  # whose mesh is compared (Python index over stages)

    def __post_init__(self):
        if self.mode not in L.RADAR_MODES:
            raise ValueError(f"mode: must be one of {', '.join(L.RADAR_MODES)}, got {self.mode!r}")
        if self.balance not in RADAR_BALANCES:
            raise ValueError(f"balance: must be one of {', '.join(RADAR_BALANCES)}, got {self.balance!r}")
        if self.target not in RADAR_TARGETS:
            raise ValueError(f"target: must be one of {', '.join(RADAR_TARGETS)}, got {self.target!r}")
        if min(self.focused_lateral_mm, self.focused_range_mm) <= 0 or self.focused_blur_mm < 0 \
                or self.smooth_iterations < 0:
            raise ValueError("focused_lateral_mm, focused_range_mm: must be > 0; focused_blur_mm, "
                             "smooth_iterations: >= 0")
        if self.weight < 0 or self.warmup_epochs < 0 or self.ramp_epochs < 0 or self.antennas < 0 or self.beta <= 0:
            raise ValueError("weight, warmup_epochs, ramp_epochs, antennas: must be >= 0; beta: > 0")


@dataclass(frozen=True)
class OptimConfig:
    """[optim]: Adam."""

    lr: float = 1e-3
    epochs: int = 500
    schedule: str = "constant"  # constant | cosine (per epoch, from lr down to lr * final_lr)
    final_lr: float = 0.0  # cosine: the last epoch's lr as a fraction of lr

    def __post_init__(self):
        if not self.lr > 0 or self.epochs < 1:
            raise ValueError(f"lr/epochs: need > 0 / >= 1, got {self.lr}, {self.epochs}")
        if self.schedule not in LR_SCHEDULES:
            raise ValueError(f"schedule: must be one of {', '.join(LR_SCHEDULES)}, got {self.schedule!r}")
        if not 0 <= self.final_lr <= 1:
            raise ValueError(f"final_lr: need 0..1, got {self.final_lr}")


@dataclass(frozen=True)
class RunConfig:
    """[run]: where and how."""

    device: str = "auto"  # auto (CUDA when available) | cpu | cuda
    amp: bool = False  # mixed precision (torch.autocast: float16 on CUDA, bfloat16 on CPU)
    checkpoint_every: int = 1  # epochs
    val_every: int = 1  # epochs between validations (the last epoch is always validated)
    val_samples: int = 4000  # surface samples per direction for the validation ASSD / HD

    def __post_init__(self):
        if self.device not in ("auto", "cpu", "cuda"):
            raise ValueError(f"device: must be auto, cpu or cuda, got {self.device!r}")
        if self.checkpoint_every < 1 or self.val_every < 1 or self.val_samples < 1:
            raise ValueError(f"checkpoint_every, val_every, val_samples: must be >= 1, got "
                             f"{self.checkpoint_every}, {self.val_every}, {self.val_samples}")


@dataclass(frozen=True)
class RefineConfig:
    """[refine]: `meshsar evaluate / predict --refine` (trainer/refine.py refine_mesh). Each step moves
    the predicted mesh down the gradient of the focused radar loss against the sample's recorded
    echo (the gradient smoothed on the mesh as in training) plus laplacian_weight times the
    Laplacian term against the prediction itself, scaled so that the vertex that moves most
    moves step_mm."""

    # Chosen on a trained run's validation samples (docs/trainer.md): 160 steps, smoothed 20 times, against
    # 20 smoothed 100 times; test samples were not looked at.
    steps: int = 160
    step_mm: float = 0.25
    smooth_iterations: int = 20
    laplacian_weight: float = 1.0

    def __post_init__(self):
        if self.steps < 0 or not self.step_mm > 0 or self.smooth_iterations < 0 or self.laplacian_weight < 0:
            raise ValueError("steps, smooth_iterations, laplacian_weight: must be >= 0; step_mm: > 0")


TABLES = {"data": DataConfig, "model": ModelConfig, "loss": LossConfig, "radar_loss": RadarLossConfig,
          "optim": OptimConfig, "run": RunConfig, "refine": RefineConfig}


@dataclass(frozen=True)
class TrainConfig:
    name: str
    seed: int = 0
    data: DataConfig = field(default_factory=DataConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    radar_loss: RadarLossConfig = field(default_factory=RadarLossConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    run: RunConfig = field(default_factory=RunConfig)
    refine: RefineConfig = field(default_factory=RefineConfig)
    text: str = ""  # the TOML it came from (kept in run folders and checkpoints)

    def __post_init__(self):
        if self.seed < 0:
            raise ValueError(f"seed: must be >= 0 (numpy's seed sequences take non-negative integers), got {self.seed}")

    def as_dict(self) -> dict:
        """Plain data (lists, not tuples), for JSON and checkpoints."""
        plain = dataclasses.asdict(self)
        del plain["text"]
        return _plain(plain)


def _plain(value):
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value


def parse_config(text: str, file: str = "<config>") -> TrainConfig:
    """Parse and validate trainer-config TOML; RecipeError naming `file` and the key."""
    data = parse_toml(text, file, {"name", "seed", *TABLES})
    if "name" not in data:
        raise RecipeError(f"{file}: missing required key 'name'")
    top = build(TrainConfig, {k: data[k] for k in ("name", "seed") if k in data}, file)
    tables = {k: build(cls, data.get(k, {}), f"{file}: [{k}]") for k, cls in TABLES.items()}
    return dataclasses.replace(top, **tables, text=text)


def load_config(path: str | os.PathLike) -> TrainConfig:
    return parse_config(read_text(path, "trainer config"), str(path))


def split_seed(split: str) -> int:
    """'seed-7' -> 7 (the split file OUT/splits/seed-7.json)."""
    match = re.fullmatch(r"seed-(\d+)", split)
    if not match:
        raise InputError(f"--split: expected seed-<N>, got {split!r}")
    return int(match.group(1))
