"""The reference SAR2Mesh trainer: `meshsar train CONFIG --data OUT [--split seed-0] [--out RUN]`.

A trainer config (manifests/train/*.toml) has top-level `name` and `seed` and the
tables [data], [model] (model.ModelConfig), [loss], [radar_loss], [optim] and
[run]; unknown keys and wrong types are errors naming the file and the key.

A run folder holds config.toml (the config as given), run.json (data, split,
dataset identity), log.csv (one row per epoch) and checkpoint.pt (tensors and
plain data only: loads with torch.load(weights_only=True)). Rerunning the same
command on the same folder resumes from its checkpoint. Under torchrun (WORLD_SIZE
> 1) the model is wrapped in DistributedDataParallel and each rank reads its own
shards; rank 0 writes the run folder.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import math
import os
import re
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import DataLoader
from tqdm import tqdm

from meshsar_builder.dataset.readers import MeshSARDataset, MeshSARIterable, collate_meshes
from meshsar_builder.dataset.shards import read_index
from meshsar_builder.pipeline.errors import InputError, RecipeError
from meshsar_builder.pipeline.io import write_bytes, write_json
from meshsar_builder.pipeline.recipe import build, parse_toml, read_text
from meshsar_builder.pipeline.seeding import seed_sequence
from meshsar_builder.radar.params import RadarParams
from meshsar_builder.trainer import losses as L
from meshsar_builder.trainer.model import ModelConfig, SAR2Mesh

CHECKPOINT = "checkpoint.pt"
LOG = "log.csv"
LOSS_TERMS = ("chamfer", "laplacian", "edge", "normal")
LOG_COLUMNS = ("epoch", "steps", "total", *LOSS_TERMS, "radar", "radar_l1", "radar_weight", "lr", "seconds")
RADAR_BALANCES = ("gradient", "none")
LR_SCHEDULES = ("constant", "cosine")


@dataclass(frozen=True)
class DataConfig:
    """[data]: what the model sees."""

    channels: tuple[str, ...] = ("intensity", "depth")  # sar channels, by name
    views: tuple[str, ...] = ()  # view names to use; empty: all (["anterior"]: the one-view ablation)
    batch_size: int = 1
    workers: int = 0  # DataLoader worker processes per rank

    def __post_init__(self):
        if not self.channels:
            raise ValueError("channels: need at least one channel")
        if self.batch_size < 1 or self.workers < 0:
            raise ValueError(f"batch_size/workers: need >= 1 / >= 0, got {self.batch_size}, {self.workers}")


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
    """[radar_loss]: L1 between the prediction's differentiable echo and the stored echo."""

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
    beta: float = 10.0  # steepness of the soft visibility
    antennas: int = 0  # antennas per view drawn each step (0: every antenna of the echo grid)
    stage: int = -1  # whose mesh is compared (Python index over stages)

    def __post_init__(self):
        if self.mode not in L.RADAR_MODES:
            raise ValueError(f"mode: must be one of {', '.join(L.RADAR_MODES)}, got {self.mode!r}")
        if self.balance not in RADAR_BALANCES:
            raise ValueError(f"balance: must be one of {', '.join(RADAR_BALANCES)}, got {self.balance!r}")
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

    def __post_init__(self):
        if self.device not in ("auto", "cpu", "cuda"):
            raise ValueError(f"device: must be auto, cpu or cuda, got {self.device!r}")
        if self.checkpoint_every < 1:
            raise ValueError(f"checkpoint_every: must be >= 1, got {self.checkpoint_every}")


TABLES = {"data": DataConfig, "model": ModelConfig, "loss": LossConfig, "radar_loss": RadarLossConfig,
          "optim": OptimConfig, "run": RunConfig}


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
    text: str = ""  # the TOML it came from (kept in run folders and checkpoints)

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


# ---------------------------------------------------------------- dataset geometry


@dataclass
class DatasetGeometry:
    """What the model and radar loss need from index.json, for the views in use.

    view_index: positions of the used views on the sar/echo view axis; frames (V, 3, 3)
    rows u, v, w; positions (V, M, 3) mm; centres (V, 3) aperture centres, mm;
    freqs (Ef,) Hz; radar: the echo-model parameters echo_torch reads.
    """

    view_names: list[str]
    view_index: list[int]
    frames: np.ndarray
    fov_mm: float
    positions: np.ndarray
    centres: np.ndarray
    freqs: np.ndarray
    radar: RadarParams

    @classmethod
    def from_index(cls, index: dict, views: tuple[str, ...] = ()) -> "DatasetGeometry":
        names = [v["name"] for v in index["views"]]
        chosen = list(views) or names
        missing = [v for v in chosen if v not in names]
        if missing:
            raise InputError(f"[data] views: {missing} not in the dataset's views {names}")
        picked = [index["views"][names.index(v)] for v in chosen]
        frames = np.array([[v["u"], v["v"], v["w"]] for v in picked], dtype=np.float64)
        r = index["radar"]
        radar = RadarParams(slope_hz_per_s=r["slope_hz_per_s"], rvp=r["rvp"], p=r["p"], kappa=r["kappa"])
        grid = index["echo_grid"]
        return cls(
            view_names=chosen, view_index=[names.index(v) for v in chosen], frames=frames,
            fov_mm=float(index["fov_mm"]),
            positions=np.array([grid["positions_mm"][v] for v in chosen], dtype=np.float64),
            centres=float(r["z0_mm"]) * frames[:, 2], freqs=np.array(grid["frequencies_hz"], dtype=np.float64),
            radar=radar,
        )


def template_radius(root: Path, split_seed_: int) -> float:
    """Mean distance of ground-truth vertices from the heart-frame origin over the train split, mm."""
    dataset = MeshSARDataset(root, "train", seed=split_seed_)
    return float(np.mean([dataset[i]["verts"].norm(dim=1).mean().item() for i in range(len(dataset))]))


# ---------------------------------------------------------------- losses of a batch


def step_generator(seed: int, epoch: int, step: int, rank: int) -> torch.Generator:
    """The CPU generator of one training step: depends only on (seed, epoch, step, rank), so resumed runs repeat."""
    state = seed_sequence(seed, "train", f"{epoch}/{step}/{rank}").generate_state(1)[0]
    return torch.Generator().manual_seed(int(state))


def batch_losses(meshes: list[tuple[torch.Tensor, torch.Tensor]], model: SAR2Mesh, batch: dict,
                 geometry: DatasetGeometry, config: TrainConfig, radar_weight: float,
                 generator: torch.Generator) -> dict[str, torch.Tensor]:
    """Weighted loss terms of one batch and their sum "total" (scalars, float32).

    meshes: the model's per-stage (input, output) vertices (B, n_k, 3) mm. Geometric
    terms are summed over stages, in units of fov/2; the radar term uses one stage.
    """
    unit = geometry.fov_mm / 2
    device = meshes[0][1].device
    targets = [L.sample_surface(v.double(), f, config.loss.chamfer_points, generator).float().to(device) / unit
               for v, f in zip(batch["verts"], batch["faces"])]  # B x (P, 3)
    terms = {name: torch.zeros((), device=device) for name in (*LOSS_TERMS, "radar", "radar_l1")}
    for k, (before, after) in enumerate(meshes):
        topo = model.topology(k)
        before, after = before.float().detach() / unit, after.float() / unit  # (B, n_k, 3)
        terms["chamfer"] = terms["chamfer"] + torch.stack([L.chamfer(p, t) for p, t in zip(after, targets)]).mean()
        terms["laplacian"] = terms["laplacian"] + L.laplacian_loss(after, before, topo["edges"])
        terms["edge"] = terms["edge"] + L.edge_loss(after, topo["edges"])
        terms["normal"] = terms["normal"] + L.normal_consistency(after, topo["faces"], topo["face_pairs"])
    for name, weight in zip(LOSS_TERMS, config.loss.weights):
        terms[name] = weight * terms[name]
    if radar_weight > 0:
        rc = config.radar_loss
        echo = batch["echo"][:, geometry.view_index]
        echo = echo.reshape(*echo.shape[:2], -1, echo.shape[-1])  # (B, V, M, Ef), rows as positions_mm
        positions = geometry.positions
        if 0 < rc.antennas < positions.shape[1]:
            pick = torch.randperm(positions.shape[1], generator=generator)[: rc.antennas].numpy()
            positions, echo = positions[:, pick], echo[:, :, pick]
        verts = meshes[rc.stage][1]
        relative = L.radar_loss(verts.float(), model.topology(rc.stage)["faces"], echo.to(device), positions,
                                geometry.centres, geometry.freqs, geometry.radar, rc.mode, rc.beta)
        terms["radar_l1"] = relative.detach()
        if rc.balance == "gradient" and torch.is_grad_enabled() and verts.requires_grad:
            terms["radar"] = radar_weight * balanced(relative, sum(terms[name] for name in LOSS_TERMS), verts)
        else:
            terms["radar"] = radar_weight * relative
    terms["total"] = sum(terms[name] for name in (*LOSS_TERMS, "radar"))
    return terms


def balanced(radar: torch.Tensor, geometric: torch.Tensor, verts: torch.Tensor) -> torch.Tensor:
    """The radar term rescaled so that its gradient on `verts` has the norm of the geometric terms' there.

    Returns s * radar in value and gradient, s = |d geometric/d verts| / |d radar/d verts| held
    constant. The radar graph is walked once: its vertex gradient is carried into the network by
    a linear surrogate (zero in value), so backward does not recompute the echo.
    """
    g_radar, = torch.autograd.grad(radar, verts)
    g_geometric, = torch.autograd.grad(geometric, verts, retain_graph=True, allow_unused=True)
    if g_geometric is None:
        return radar.detach() * 0
    scale = g_geometric.norm() / g_radar.norm().clamp_min(1e-30)
    surrogate = (verts * (scale * g_radar).to(verts.dtype)).sum()
    return scale * radar.detach() + (surrogate - surrogate.detach())


def radar_weight_at(config: TrainConfig, epoch: int) -> float:
    """The radar loss weight of an epoch (0-based): 0 during the warm-up, then a linear ramp over ramp_epochs."""
    rc = config.radar_loss
    if epoch < rc.warmup_epochs:
        return 0.0
    return rc.weight * min(1.0, (epoch - rc.warmup_epochs + 1) / (rc.ramp_epochs + 1))


def lr_at(config: TrainConfig, epoch: int) -> float:
    """The learning rate of an epoch (0-based) under [optim] schedule."""
    oc = config.optim
    if oc.schedule == "constant" or oc.epochs == 1:
        return oc.lr
    progress = epoch / (oc.epochs - 1)
    return oc.lr * (oc.final_lr + (1 - oc.final_lr) * 0.5 * (1 + math.cos(math.pi * progress)))


# ---------------------------------------------------------------- distribution and devices


def distributed() -> tuple[int, int, int]:
    """(rank, world size, local rank); initialises the process group when torchrun set WORLD_SIZE > 1."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world > 1 and not torch.distributed.is_initialized():
        torch.distributed.init_process_group("nccl" if torch.cuda.is_available() else "gloo")
    if torch.distributed.is_initialized():
        return torch.distributed.get_rank(), torch.distributed.get_world_size(), int(os.environ.get("LOCAL_RANK", "0"))
    return 0, 1, 0


def pick_device(name: str, local_rank: int) -> torch.device:
    if name == "cuda" or (name == "auto" and torch.cuda.is_available()):
        if not torch.cuda.is_available():
            raise InputError("[run] device = cuda, but CUDA is not available")
        return torch.device("cuda", local_rank)
    return torch.device("cpu")


def all_reduce(values: torch.Tensor, op=None) -> torch.Tensor:
    """Sum (or `op`) of a CPU tensor over ranks; itself when not distributed."""
    if torch.distributed.is_initialized():
        on = values.cuda() if torch.distributed.get_backend() == "nccl" else values.clone()
        torch.distributed.all_reduce(on, op or torch.distributed.ReduceOp.SUM)
        return on.cpu()
    return values


def steps_this_epoch(dataset: MeshSARIterable, batch_size: int, workers: int, rank: int, world: int) -> int:
    """Batches every rank can run this epoch: the fewest over ranks, so DDP's collectives stay paired.

    Each DataLoader worker batches its own shards, so a rank's batches are the sum over its workers.
    """
    consumers = max(workers, 1)
    mine = sum(math.ceil(sum(len(rows) for _, rows in dataset.assignment(rank * consumers + w, world * consumers))
                         / batch_size) for w in range(consumers))
    return int(all_reduce(torch.tensor([mine]), torch.distributed.ReduceOp.MIN if world > 1 else None)[0])


# ---------------------------------------------------------------- checkpoints and logs


def save_checkpoint(path: Path, state: dict) -> None:
    buffer = io.BytesIO()
    torch.save(state, buffer)
    write_bytes(path, buffer.getvalue())


def load_checkpoint(path: Path, device: torch.device | str = "cpu") -> dict:
    """A run's checkpoint; weights_only=True, since run folders are shared like datasets."""
    return torch.load(path, map_location=device, weights_only=True)


def build_model(config: TrainConfig, info: dict) -> SAR2Mesh:
    """The model a checkpoint's `info` describes (frames, fov_mm, channels, template_radius_mm)."""
    return SAR2Mesh(config.model, np.asarray(info["frames"]), info["fov_mm"], len(info["channels"]),
                    info["template_radius_mm"])


def load_run(run: str | os.PathLike, device: torch.device | str = "cpu") -> tuple[SAR2Mesh, TrainConfig, dict]:
    """(model in eval mode, config, checkpoint info) of a run folder."""
    run = Path(run)
    if not (run / CHECKPOINT).exists():
        raise InputError(f"{run}: no {CHECKPOINT}; train first with `meshsar train CONFIG --data OUT --out {run}`")
    state = load_checkpoint(run / CHECKPOINT, device)
    config = parse_config(state["config_text"], str(run / "config.toml"))
    model = build_model(config, state["info"]).to(device)
    model.load_state_dict(state["model"])
    return model.eval(), config, state["info"]


def write_log(path: Path, rows: list[dict]) -> None:
    text = io.StringIO()
    writer = csv.DictWriter(text, fieldnames=LOG_COLUMNS)
    writer.writeheader()
    writer.writerows(rows)
    write_bytes(path, text.getvalue().encode("utf-8"))


def read_log(path: Path) -> list[dict]:
    if not path.exists():
        return []
    with open(path, newline="", encoding="utf-8") as f:
        # Columns a log written by an older version lacks read as 0.
        return [{k: (int(v) if k in ("epoch", "steps") else float(v or 0)) for k, v in row.items()}
                for row in csv.DictReader(f, restval="")]


# ---------------------------------------------------------------- training


@dataclass
class TrainResult:
    run: Path
    model: SAR2Mesh  # unwrapped (no DDP), on its training device
    log: list[dict]  # log.csv rows so far, one per epoch


def train(config: TrainConfig | str | os.PathLike, data: str | os.PathLike, split: str = "seed-0",
          out: str | os.PathLike | None = None, progress: bool = True) -> TrainResult:
    """Train (or resume) a run; returns its folder, model and epoch log.

    data: a build folder with index.json and splits/; split: seed-<N>; out: the run
    folder (default DATA/runs/<config name>-<split>).
    """
    config = config if isinstance(config, TrainConfig) else load_config(config)
    data = Path(data)
    seed_ = split_seed(split)
    run = Path(out) if out is not None else data / "runs" / f"{config.name}-{split}"
    rank, world, local_rank = distributed()
    device = pick_device(config.run.device, local_rank)
    index = read_index(data)
    geometry = DatasetGeometry.from_index(index, config.data.views)
    state = load_checkpoint(run / CHECKPOINT, device) if (run / CHECKPOINT).exists() else None
    if state is not None and state["config_text"] != config.text:
        raise InputError(f"{run}: holds a run of a different config; give another --out or remove it")
    info = state["info"] if state is not None else {
        "view_names": geometry.view_names, "frames": geometry.frames.tolist(), "fov_mm": geometry.fov_mm,
        "channels": list(config.data.channels), "data": str(data), "split": split,
        "recipe": index["recipe"], "recipe_sha256": index["recipe_sha256"],
        "template_radius_mm": config.model.template_radius_mm or template_radius(data, seed_),
    }
    torch.manual_seed(config.seed)
    model = build_model(config, info).to(device)
    optimizer = torch.optim.Adam(model.parameters(), lr=config.optim.lr)
    amp = config.run.amp
    scaler = torch.amp.GradScaler(device.type, enabled=amp and device.type == "cuda")
    start = 0
    if state is not None:
        model.load_state_dict(state["model"])
        optimizer.load_state_dict(state["optimizer"])
        scaler.load_state_dict(state["scaler"])
        start = state["epoch"]
    log = [row for row in read_log(run / LOG) if row["epoch"] < start]
    if rank == 0:
        write_bytes(run / "config.toml", config.text.encode("utf-8"))
        write_json(run / "run.json", {**info, "config": config.as_dict(), "world_size": world})
    # Encoder scales no stage samples leave parameters without gradients, which DDP must be told.
    unused = set(range(len(config.model.encoder_channels))) - {s for st in config.model.stage_scales for s in st}
    net = torch.nn.parallel.DistributedDataParallel(
        model, device_ids=[device.index] if device.type == "cuda" else None, find_unused_parameters=bool(unused),
    ) if world > 1 else model
    dataset = MeshSARIterable(data, "train", seed=seed_, shuffle=True, channels=list(config.data.channels),
                              rank=rank, world_size=world)
    loader = DataLoader(dataset, batch_size=config.data.batch_size, collate_fn=collate_meshes,
                        num_workers=config.data.workers)
    autocast_dtype = torch.float16 if device.type == "cuda" else torch.bfloat16
    bar = tqdm(total=config.optim.epochs, initial=start, desc=f"train {config.name}", unit="epoch",
               disable=not progress or rank != 0)
    for epoch in range(start, config.optim.epochs):
        began = time.perf_counter()
        dataset.set_epoch(epoch)
        steps = steps_this_epoch(dataset, config.data.batch_size, config.data.workers, rank, world)
        radar_weight = radar_weight_at(config, epoch)
        lr = lr_at(config, epoch)
        for group in optimizer.param_groups:
            group["lr"] = lr
        sums = torch.zeros(len(LOSS_TERMS) + 3, dtype=torch.float64)  # terms, radar, radar_l1, total
        model.train()
        for step, batch in zip(range(steps), loader):
            sar = batch["sar"][:, geometry.view_index].to(device)  # (B, V, C, H, W)
            with torch.autocast(device.type, dtype=autocast_dtype, enabled=amp):
                meshes = net(sar)
            terms = batch_losses(meshes, model, batch, geometry, config, radar_weight,
                                 step_generator(config.seed, epoch, step, rank))
            optimizer.zero_grad(set_to_none=True)
            scaler.scale(terms["total"]).backward()
            scaler.step(optimizer)
            scaler.update()
            sums += torch.tensor([terms[k].item() for k in (*LOSS_TERMS, "radar", "radar_l1", "total")],
                                 dtype=torch.float64)
        means = all_reduce(sums) / max(1, steps * world)
        row = {"epoch": epoch, "steps": steps, **dict(zip((*LOSS_TERMS, "radar", "radar_l1", "total"), means.tolist())),
               "radar_weight": radar_weight, "lr": lr, "seconds": time.perf_counter() - began}
        log.append(row)
        bar.set_postfix(loss=f"{row['total']:.4g}", chamfer=f"{row['chamfer']:.3g}")
        bar.update()
        done = epoch + 1
        if rank == 0:
            write_log(run / LOG, log)
        if rank == 0 and (done % config.run.checkpoint_every == 0 or done == config.optim.epochs):
            save_checkpoint(run / CHECKPOINT, {
                "epoch": done, "model": model.state_dict(), "optimizer": optimizer.state_dict(),
                "scaler": scaler.state_dict(), "config_text": config.text, "info": info,
            })
    bar.close()
    return TrainResult(run=run, model=model, log=log)
