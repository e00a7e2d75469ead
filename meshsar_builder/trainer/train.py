"""The reference SAR2Mesh trainer: `meshsar train CONFIG --data OUT [--split seed-0] [--out RUN]`.

The config (manifests/train/*.toml) is described in trainer.config.

A run folder holds config.toml (the config as given), run.json (data, split,
dataset identity, the validation ids, the devices it trained on), log.csv (one row per epoch: every loss
term, also per stage, and the validation metrics of the epochs that had them),
checkpoint.pt (the last epoch) and best.pt (the best validation Dice so far),
both tensors and plain data only: they load with torch.load(weights_only=True).
With `tensorboard` installed the log's numbers also go to tb/ as event files.
Rerunning the same command on the same folder resumes from its checkpoint.

Validation: a seeded part of the train split (val_fraction), grouped by subject
like the splits themselves (dataset.splits.make_split), never the test split.

Under torchrun (WORLD_SIZE > 1) the model is wrapped in DistributedDataParallel.
Each epoch's sample order (seeded by (seed, epoch)) is dealt sample by sample over
the ranks, so every training sample is seen exactly once per epoch whatever the
shard sizes; steps where a rank has fewer samples weight its loss by its share of
the global batch (0 for a rank with none), so the averaged gradient is that of the
global batch's mean loss. Rank 0 validates and writes the run folder.
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import io
import math
import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import DataLoader
from tqdm import tqdm

from meshsar_builder.dataset.readers import MeshSARDataset, collate_meshes, split_ids
from meshsar_builder.dataset.shards import read_index
from meshsar_builder.dataset.splits import make_split
from meshsar_builder.pipeline.errors import InputError
from meshsar_builder.pipeline.io import read_json, write_bytes, write_json
from meshsar_builder.pipeline.seeding import item_rng, seed_sequence
from meshsar_builder.trainer import losses as L
from meshsar_builder.trainer.config import TrainConfig, load_config, parse_config, split_seed
from meshsar_builder.trainer.dataset_geometry import DatasetGeometry
from meshsar_builder.trainer.implicit import ImplicitSAR, occupancy_loss
from meshsar_builder.trainer.metrics import mesh_metrics
from meshsar_builder.trainer.model import SAR2Mesh

CHECKPOINT = "checkpoint.pt"
BEST = "best.pt"
LOG = "log.csv"
LOSS_TERMS = ("chamfer", "laplacian", "edge", "normal")
SUMMED = (*LOSS_TERMS, "radar", "radar_l1", "total")  # per-sample means of a batch, logged per epoch
VAL_METRICS = ("dice", "jaccard", "assd_mm", "hd_mm", "hd95_mm", "ane_rad", "anld", "si_pct")
INT_COLUMNS = ("epoch", "steps", "samples")
def validation_split(root: Path, index: dict, split_seed_: int, fraction: float) -> tuple[list[str], list[str]]:
    """(train ids, validation ids) of the train split of seed-<split_seed_>, in dataset order.

    The validation part is `fraction` of the train split, grouped by subject and seeded like
    the splits (make_split on the train samples only, seeded from the split's seed).
    """
    ids = split_ids(root, index, "train", split_seed_)
    if fraction == 0:
        return ids, []
    chosen = set(ids)
    sub = {"samples": {sid: index["samples"][sid] for sid in ids},
           "shards": [{"sample_ids": [s for s in shard["sample_ids"] if s in chosen]} for shard in index["shards"]]}
    seed = int(seed_sequence(split_seed_, "trainer", "validation").generate_state(1)[0])
    split = make_split(sub, seed, {"train": 1 - fraction, "val": fraction})
    return split["train"], split["val"]


class Subset(torch.utils.data.Dataset):
    """The samples of a MeshSARDataset with the given ids, in that order."""

    def __init__(self, dataset: MeshSARDataset, ids: list[str]):
        position = {sid: k for k, sid in enumerate(dataset.ids)}
        self.dataset, self.ids, self.rows = dataset, list(ids), [position[sid] for sid in ids]

    def __len__(self) -> int:
        return len(self.rows)

    def __getitem__(self, i: int) -> dict:
        return self.dataset[self.rows[i]]


def template_radius(dataset: torch.utils.data.Dataset) -> float:
    """Mean distance of ground-truth vertices from the heart-frame origin over a dataset's samples, mm."""
    return float(np.mean([dataset[i]["verts"].norm(dim=1).mean().item() for i in range(len(dataset))]))


# ---------------------------------------------------------------- losses of a batch


def sample_generators(seed: int, epoch: int, sample_ids: list[str]) -> list[torch.Generator]:
    """CPU generators of a batch's samples in an epoch: each depends only on (seed, epoch, sample id), so
    resumed runs repeat and a sample draws the same numbers whichever rank or batch it falls in."""
    return [torch.Generator().manual_seed(int(seed_sequence(seed, "train", f"{epoch}/{sid}").generate_state(1)[0]))
            for sid in sample_ids]


_MASKS = ThreadPoolExecutor(1)  # batch_losses' radar masks, beside the geometric terms


def batch_losses(meshes: list[tuple[torch.Tensor, torch.Tensor]], model: SAR2Mesh, batch: dict,
                 geometry: DatasetGeometry, config: TrainConfig, radar_weight: float,
                 generators: list[torch.Generator]) -> dict[str, torch.Tensor]:
    """Weighted loss terms of one batch and their sum "total" (scalars, float32; means over the batch).

    meshes: the model's per-stage (input, output) vertices (B, n_k, 3) mm. Geometric
    terms are summed over stages, in units of fov/2 ("<term>_s<k>": stage k's share);
    the radar term uses one stage. generators: one CPU generator per sample (sample_generators):
    its Chamfer target points, and for the first the radar loss's antennas.
    """
    unit = geometry.fov_mm / 2
    device = meshes[0][1].device
    rc, params, masks = config.radar_loss, focused_params(config.radar_loss), None
    if radar_weight > 0 and rc.mode in L.FOCUSED_MODES:  # Embree masks traced in a thread beside the geometric terms
        from meshsar_builder.radar.differentiable import occlusion_masks

        setup = geometry.focused_setup(params)
        masks = _MASKS.submit(occlusion_masks, meshes[rc.stage][1].detach().float(), model.topology(rc.stage)["faces"], setup.probes)
    targets = [L.sample_surface(v.double(), f, config.loss.chamfer_points, g).float().to(device) / unit
               for v, f, g in zip(batch["verts"], batch["faces"], generators)]  # B x (P, 3)
    terms = {name: torch.zeros((), device=device) for name in ("radar", "radar_l1")}
    for k, (before, after) in enumerate(meshes):
        topo = model.topology(k)
        before, after = before.float().detach() / unit, after.float() / unit  # (B, n_k, 3)
        stage = (torch.stack([L.chamfer(p, t) for p, t in zip(after, targets)]).mean(),
                 L.laplacian_loss(after, before, topo["edges"]), L.edge_loss(after, topo["edges"]),
                 L.normal_consistency(after, topo["faces"], topo["face_pairs"]))
        for name, weight, value in zip(LOSS_TERMS, config.loss.weights, stage):
            terms[f"{name}_s{k}"] = weight * value
    for name in LOSS_TERMS:
        terms[name] = sum(terms[f"{name}_s{k}"] for k in range(len(meshes)))
    if masks is not None:
        targets = geometry.focused_targets(batch, params, rc.target).to(device)
        topo = model.topology(rc.stage)
        verts = meshes[rc.stage][1]
        smoothed = L.smooth_gradient(verts.float(), topo["edges"], rc.smooth_iterations)
        relative = L.focused_radar_loss(smoothed, topo["faces"], targets, setup, masks.result(), rc.mode)
        terms["radar_l1"] = relative.detach()
        if rc.balance == "gradient" and torch.is_grad_enabled() and verts.requires_grad:
            terms["radar"] = radar_weight * L.balanced(relative, sum(terms[name] for name in LOSS_TERMS), verts)
        else:
            terms["radar"] = radar_weight * relative
    elif radar_weight > 0:
        echo = geometry.echo_targets(batch, rc.target)  # (B, V, M, F)
        positions = geometry.positions
        if 0 < rc.antennas < positions.shape[1]:
            pick = torch.randperm(positions.shape[1], generator=generators[0])[: rc.antennas].numpy()
            positions, echo = positions[:, pick], echo[:, :, pick]
        verts = meshes[rc.stage][1]
        relative = L.radar_loss(verts.float(), model.topology(rc.stage)["faces"], echo.to(device), positions,
                                geometry.centres, geometry.freqs, geometry.radar, rc.mode, rc.beta)
        terms["radar_l1"] = relative.detach()
        if rc.balance == "gradient" and torch.is_grad_enabled() and verts.requires_grad:
            terms["radar"] = radar_weight * L.balanced(relative, sum(terms[name] for name in LOSS_TERMS), verts)
        else:
            terms["radar"] = radar_weight * relative
    terms["total"] = sum(terms[name] for name in (*LOSS_TERMS, "radar"))
    return terms


def focused_params(rc):
    """The FocusedParams of a [radar_loss] table."""
    from meshsar_builder.radar.focused import FocusedParams

    return FocusedParams(lateral_mm=rc.focused_lateral_mm, range_mm=rc.focused_range_mm, blur_mm=rc.focused_blur_mm)


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


def autocast_factory(device: torch.device, amp: bool):
    """The forward's autocast context-manager factory: float16 on CUDA, bfloat16 on a CPU; off unless amp."""
    dtype = torch.float16 if device.type == "cuda" else torch.bfloat16
    return lambda: torch.autocast(device.type, dtype=dtype, enabled=amp)


def all_reduce(values: torch.Tensor) -> torch.Tensor:
    """Sum of a CPU tensor over ranks; itself when not distributed."""
    if torch.distributed.is_initialized():
        on = values.cuda() if torch.distributed.get_backend() == "nccl" else values.clone()
        torch.distributed.all_reduce(on)
        return on.cpu()
    return values


def epoch_batches(n: int, batch_size: int, world: int, rank: int, seed: int, epoch: int) -> list[tuple[list[int], float]]:
    """This rank's batches of an epoch over n samples: per step (sample positions, loss weight).

    The epoch's permutation (seeded by (seed, epoch): every rank agrees) is dealt one sample
    at a time over the ranks, so the ranks' samples cover each sample exactly once. Every
    rank runs as many steps as rank 0 (which has the most), so DDP's collectives pair up; a
    step's weight is (this rank's samples x world / the step's samples over all ranks), which
    makes DDP's gradient mean the mean over the step's global batch. A rank out of samples
    repeats its first with weight 0.
    """
    if n < world:
        raise InputError(f"{n} training sample(s) for {world} ranks: every rank needs at least one")
    order = item_rng(seed, "trainer", f"epoch-{epoch}").permutation(n).tolist()
    dealt = [order[r::world] for r in range(world)]
    steps = math.ceil(len(dealt[0]) / batch_size)
    batches = []
    for step in range(steps):
        chunks = [d[step * batch_size : (step + 1) * batch_size] for d in dealt]
        total = sum(len(c) for c in chunks)
        mine = chunks[rank]
        batches.append((mine, len(mine) * world / total) if mine else (dealt[rank][:1], 0.0))
    return batches


# ---------------------------------------------------------------- checkpoints and logs


def save_checkpoint(path: Path, state: dict) -> None:
    buffer = io.BytesIO()
    torch.save(state, buffer)
    write_bytes(path, buffer.getvalue())


def load_checkpoint(path: Path, device: torch.device | str = "cpu") -> dict:
    """A run's checkpoint; weights_only=True, since run folders are shared like datasets."""
    return torch.load(path, map_location=device, weights_only=True)


def same_run(stored_text: str, config: TrainConfig, until: int | None = None) -> bool:
    """Whether a checkpoint's config (its TOML text) describes the same run as `config`: equal in every value
    but [run] device (where a run trains is not part of what it is) and [refine] (it acts after training).

    until: only epochs 0..until-1 must train alike: the name and radar weight may differ where radar_weight_at
    agrees on them (a radar ablation's warm-up), and all of [radar_loss] where it is 0 (no step computed it)."""
    stored = parse_config(stored_text)
    stored = dataclasses.replace(stored, run=dataclasses.replace(stored.run, device=config.run.device),
                                 refine=config.refine, text="")
    if until is not None and all(radar_weight_at(stored, e) == radar_weight_at(config, e) for e in range(until)):
        radar = config.radar_loss if not any(radar_weight_at(config, e) for e in range(until)) else \
            dataclasses.replace(stored.radar_loss, weight=config.radar_loss.weight)
        stored = dataclasses.replace(stored, name=config.name, radar_loss=radar)
    return stored == dataclasses.replace(config, text="")


def build_model(config: TrainConfig, info: dict) -> SAR2Mesh | ImplicitSAR:
    """The model a checkpoint's `info` describes (frames, fov_mm, channels, template_radius_mm), of [model] kind."""
    if config.model.kind == "implicit":
        return ImplicitSAR(config.model, np.asarray(info["frames"]), info["fov_mm"], len(info["channels"]))
    return SAR2Mesh(config.model, np.asarray(info["frames"]), info["fov_mm"], len(info["channels"]),
                    info["template_radius_mm"])


def loss_names(config: TrainConfig) -> list[str]:
    """The loss terms step_terms returns for a config's model kind (log.csv's loss columns)."""
    if config.model.kind == "implicit":
        return ["occupancy", "total"]
    return [*SUMMED, *(f"{n}_s{k}" for k in range(config.model.stages) for n in LOSS_TERMS)]


def step_terms(net: torch.nn.Module, model: SAR2Mesh | ImplicitSAR, batch: dict, sar: torch.Tensor,
               geometry: DatasetGeometry, config: TrainConfig, radar_weight: float,
               generators: list[torch.Generator], autocast=contextlib.nullcontext) -> dict[str, torch.Tensor]:
    """The loss terms (loss_names) of one batch: sar (B, V, C, H, W) on the model's device; net: the model or
    its DDP wrapper; autocast: a context-manager factory the forward runs under."""
    if isinstance(model, ImplicitSAR):
        with autocast():
            return occupancy_loss(net, model, batch, sar, generators)
    with autocast():
        meshes = net(sar)
    return batch_losses(meshes, model, batch, geometry, config, radar_weight, generators)


def load_run(run: str | os.PathLike, device: torch.device | str = "cpu",
             checkpoint: str = "best") -> tuple[SAR2Mesh, TrainConfig, dict]:
    """(model in eval mode, config, checkpoint info) of a run folder.

    checkpoint: "best" (best.pt, the best validation Dice; the last epoch's checkpoint.pt
    when the run had no validation) or "last" (checkpoint.pt).
    """
    run = Path(run)
    if checkpoint not in ("best", "last"):
        raise InputError(f"checkpoint: must be best or last, got {checkpoint!r}")
    if not (run / CHECKPOINT).exists():
        raise InputError(f"{run}: no {CHECKPOINT}; train first with `meshsar train CONFIG --data OUT --out {run}`")
    path = run / BEST if checkpoint == "best" and (run / BEST).exists() else run / CHECKPOINT
    state = load_checkpoint(path, device)
    own = run / "config.toml"  # the checkpoint's config but [refine], which acts after training (same_run): own's
    config = parse_config(state["config_text"], str(own))
    config = dataclasses.replace(config, refine=load_config(own).refine) if own.exists() else config
    model = build_model(config, state["info"]).to(device)
    model.load_state_dict(state["model"])
    return model.eval(), config, {**state["info"], "checkpoint": path.name, "epoch": state["epoch"]}


def log_columns(config: TrainConfig) -> list[str]:
    """log.csv's columns for a config."""
    return [*INT_COLUMNS, *loss_names(config), "val_total", *(f"val_{m}" for m in VAL_METRICS),
            "radar_weight", "lr", "seconds"]


def write_log(path: Path, rows: list[dict], columns: list[str]) -> None:
    """Rows as CSV; None (no validation that epoch) is an empty cell."""
    text = io.StringIO()
    writer = csv.DictWriter(text, fieldnames=columns)
    writer.writeheader()
    writer.writerows(rows)
    write_bytes(path, text.getvalue().encode("utf-8"))


def read_log(path: Path) -> list[dict]:
    """log.csv rows; empty cells (and columns an older log lacks) read as None."""
    if not path.exists():
        return []
    with open(path, newline="", encoding="utf-8") as f:
        return [{k: None if v in ("", None) else int(v) if k in INT_COLUMNS else float(v) for k, v in row.items()}
                for row in csv.DictReader(f, restval="")]


def tensorboard_writer(run: Path):
    """A SummaryWriter on run/tb when `tensorboard` is installed (the optional extra), else None."""
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError:
        return None
    return SummaryWriter(str(run / "tb"))


def validate(model: SAR2Mesh | ImplicitSAR, dataset: torch.utils.data.Dataset, geometry: DatasetGeometry,
             config: TrainConfig, device: torch.device) -> dict[str, float]:
    """Mean loss ("total", radar off) and mean metrics (VAL_METRICS) of the predicted meshes over a dataset."""
    model.eval()
    totals, rows = [], []
    with torch.no_grad():
        for i in range(len(dataset)):
            batch = collate_meshes([dataset[i]])
            sar = batch["sar"][:, geometry.view_index].to(device)
            totals.append(step_terms(model, model, batch, sar, geometry, config, 0.0,
                                     sample_generators(config.seed, -1, batch["sample_id"]))["total"].item())
            rows.append(mesh_metrics(*model.predict_mesh(sar[0]), batch["verts"][0].double().numpy(),
                                     batch["faces"][0].numpy(), samples=config.run.val_samples, seed=i))
    model.train()
    return {"total": float(np.mean(totals)), **{m: float(np.mean([r[m] for r in rows])) for m in VAL_METRICS}}


# ---------------------------------------------------------------- training


@dataclass
class TrainResult:
    run: Path
    model: SAR2Mesh  # unwrapped (no DDP), on its training device
    log: list[dict]  # log.csv rows so far, one per epoch


def train(config: TrainConfig | str | os.PathLike, data: str | os.PathLike, split: str = "seed-0",
          out: str | os.PathLike | None = None, progress: bool = True, device: str | None = None,
          until: int | None = None) -> TrainResult:
    """Train (or resume) a run; returns its folder, model and epoch log.

    data: a build folder with index.json and splits/; split: seed-<N>; out: the run
    folder (default DATA/runs/<config name>-<split>); device: overrides [run] device
    (where a run trains is not part of what it is: a run resumes on another device);
    until: stop after this many epochs with a checkpoint there (the run resumes later).
    """
    config = config if isinstance(config, TrainConfig) else load_config(config)
    if device is not None:
        config = dataclasses.replace(config, run=dataclasses.replace(config.run, device=device))
    data = Path(data)
    seed_ = split_seed(split)
    run = Path(out) if out is not None else data / "runs" / f"{config.name}-{split}"
    rank, world, local_rank = distributed()
    device = pick_device(config.run.device, local_rank)
    index = read_index(data)
    geometry = DatasetGeometry.from_index(index, config.data.views)
    train_ids, val_ids = validation_split(data, index, seed_, config.data.val_fraction)
    recorded = config.radar_loss.target == "recorded" and geometry.full_radar is not None
    every = MeshSARDataset(data, "train", seed=seed_, channels=list(config.data.channels), noisy_loss_echo=recorded)
    train_set, val_set = Subset(every, train_ids), Subset(every, val_ids)
    state = load_checkpoint(run / CHECKPOINT, device) if (run / CHECKPOINT).exists() else None
    if state is not None and not same_run(state["config_text"], config, until=until):  # until: those epochs alike
        raise InputError(f"{run}: holds a run of a different config; give another --out or remove it")
    info = state["info"] if state is not None else {
        "view_names": geometry.view_names, "frames": geometry.frames.tolist(), "fov_mm": geometry.fov_mm,
        "channels": list(config.data.channels), "data": str(data), "split": split,
        "recipe": index["recipe"], "recipe_sha256": index["recipe_sha256"],
        "template_radius_mm": config.model.template_radius_mm or template_radius(train_set),
    }
    torch.manual_seed(config.seed)
    model = build_model(config, info).to(device)
    optimizer = torch.optim.Adam(model.parameters(), lr=config.optim.lr)
    amp = config.run.amp
    scaler = torch.amp.GradScaler(device.type, enabled=amp and device.type == "cuda")
    start, best_dice = 0, -1.0
    if state is not None:
        model.load_state_dict(state["model"])
        optimizer.load_state_dict(state["optimizer"])
        scaler.load_state_dict(state["scaler"])
        start, best_dice = state["epoch"], state.get("best_dice", -1.0)
    end = config.optim.epochs if until is None else min(until, config.optim.epochs)
    log = [row for row in read_log(run / LOG) if row["epoch"] < start]
    columns = log_columns(config)
    board = tensorboard_writer(run) if rank == 0 else None
    if rank == 0:
        # config.toml and the config in run.json are the run's first; a resume that trains adds its device.
        first = read_json(run / "run.json") if state is not None and (run / "run.json").exists() else {}
        if not first:
            write_bytes(run / "config.toml", config.text.encode("utf-8"))
        devices = first.get("devices", [])
        if start < end:
            devices = [*devices, f"{device} ({torch.cuda.get_device_name(device)})" if device.type == "cuda" else "cpu"]
        write_json(run / "run.json", {**info, "config": first.get("config", config.as_dict()), "world_size": world,
                                      "devices": list(dict.fromkeys(devices)),
                                      "train_ids": train_ids, "val_ids": val_ids})
    # Encoder scales no stage samples leave parameters without gradients, which DDP must be told.
    unused = set(range(len(config.model.encoder_channels))) - {s for st in config.model.stage_scales for s in st}
    net = torch.nn.parallel.DistributedDataParallel(
        model, device_ids=[device.index] if device.type == "cuda" else None, find_unused_parameters=bool(unused),
    ) if world > 1 else model
    autocast = autocast_factory(device, amp)
    bar = tqdm(total=end, initial=min(start, end), desc=f"train {config.name}", unit="epoch",
               disable=not progress or rank != 0)
    for epoch in range(start, end):
        began = time.perf_counter()
        batches = epoch_batches(len(train_set), config.data.batch_size, world, rank, config.seed, epoch)
        loader = DataLoader(train_set, batch_sampler=[b for b, _ in batches], collate_fn=collate_meshes,
                            num_workers=config.data.workers)
        radar_weight = radar_weight_at(config, epoch)
        lr = lr_at(config, epoch)
        for group in optimizer.param_groups:
            group["lr"] = lr
        names = loss_names(config)
        sums = torch.zeros(len(names) + 1, dtype=torch.float64)  # per-sample sums of the terms, then samples
        model.train()
        for batch, (_, weight) in zip(loader, batches):
            sar = batch["sar"][:, geometry.view_index].to(device)  # (B, V, C, H, W)
            terms = step_terms(net, model, batch, sar, geometry, config, radar_weight,
                               sample_generators(config.seed, epoch, batch["sample_id"]), autocast)
            optimizer.zero_grad(set_to_none=True)
            scaler.scale(terms["total"] * weight).backward()
            scaler.step(optimizer)
            scaler.update()
            if weight > 0:
                size = len(batch["verts"])
                sums += torch.tensor([size * terms[k].item() for k in names] + [size], dtype=torch.float64)
        sums = all_reduce(sums)
        row = {"epoch": epoch, "steps": len(batches), "samples": int(sums[-1]),
               **dict(zip(names, (sums[:-1] / sums[-1]).tolist())), "radar_weight": radar_weight, "lr": lr}
        done = epoch + 1
        validated = rank == 0 and bool(val_ids) and (done % config.run.val_every == 0 or done == config.optim.epochs)
        val = validate(model, val_set, geometry, config, device) if validated else {}
        row.update({f"val_{k}": val.get(k) for k in ("total", *VAL_METRICS)}, seconds=time.perf_counter() - began)
        log.append(row)
        bar.set_postfix(loss=f"{row['total']:.4g}", **({"val_dice": f"{val['dice']:.3f}"} if val else {}))
        bar.update()
        if rank != 0:
            continue
        write_log(run / LOG, log, columns)
        if board is not None:
            for key, value in row.items():
                if key != "epoch" and value is not None:
                    board.add_scalar(key, value, epoch)
            board.flush()
        if val and val["dice"] > best_dice:
            best_dice = val["dice"]
            save_checkpoint(run / BEST, {"epoch": done, "model": model.state_dict(), "config_text": config.text,
                                         "info": info, "val": val})
        if done % config.run.checkpoint_every == 0 or done == end:
            save_checkpoint(run / CHECKPOINT, {
                "epoch": done, "model": model.state_dict(), "optimizer": optimizer.state_dict(),
                "scaler": scaler.state_dict(), "config_text": config.text, "info": info, "best_dice": best_dice,
            })
    bar.close()
    if board is not None:
        board.close()
    return TrainResult(run=run, model=model, log=log)
