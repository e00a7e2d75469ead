"""What the trainer reads of a build's index.json: the views in use, their frames and the radar (DatasetGeometry)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from meshsar_builder.pipeline.errors import InputError
from meshsar_builder.radar.params import RadarParams


@dataclass
class DatasetGeometry:
    """What the model and radar loss need from index.json, for the views in use.

    view_index: positions of the used views on the sar/echo view axis; frames (V, 3, 3)
    rows u, v, w; positions (V, M, 3) mm and freqs (F,) Hz: where the raw and profile radar
    losses compare echoes, the loss grid (echo_clean's; a build without one: the echo grid);
    centres (V, 3) aperture centres, mm; radar: the build's RadarParams, every key its index
    records (aperture, probes, z0_mm, reflectivity, ...: echo_torch reads them).
    """

    view_names: list[str]
    view_index: list[int]
    frames: np.ndarray
    fov_mm: float
    positions: np.ndarray
    centres: np.ndarray
    freqs: np.ndarray
    radar: RadarParams
    # the build's full radar (loss grid included), for the focused loss; None for format-1 indexes
    full_radar: RadarParams | None = None
    _focused: dict = field(default_factory=dict, repr=False)  # FocusedParams -> FocusedSetup
    _targets: dict = field(default_factory=dict, repr=False)  # (params, target, sample id) -> (V, S, H, W)

    def focused_setup(self, params):
        """The FocusedSetup of the views in use for FocusedParams `params` (built once: ~1-10 s)."""
        from meshsar_builder.radar.focused import FocusedSetup

        if self.full_radar is None:
            raise InputError("[radar_loss] mode = \"focused\" needs a build with a loss grid (shards format 2); "
                             "rebuild the data, or use mode = \"raw\" or \"profile\"")
        if params not in self._focused:
            self._focused[params] = FocusedSetup(self.full_radar, self.view_names, params)
        return self._focused[params]

    def focused_targets(self, batch: dict, params, target: str) -> torch.Tensor:
        """(B, V, S, H, W) float32 targets of a batch, each sample's focused once and kept (by sample id);
        batch["radar_targets"], when given, is used as it is (the trainer benchmark's synthetic batch)."""
        if "radar_targets" in batch:
            return batch["radar_targets"]
        setup = self.focused_setup(params)
        out = []
        for k, sid in enumerate(batch["sample_id"]):
            key = (params, target, sid)
            if key not in self._targets:
                echo = self._loss_grid_echo(batch, target)[k][self.view_index]
                sigma = 0.0 if target == "clean" else batch["noise_sigma"][k][self.view_index].numpy()
                self._targets[key] = torch.from_numpy(setup.target(echo.numpy(), sigma))
            out.append(self._targets[key])
        return torch.stack(out)

    @classmethod
    def from_index(cls, index: dict, views: tuple[str, ...] = ()) -> "DatasetGeometry":
        names = [v["name"] for v in index["views"]]
        chosen = list(views) or names
        missing = [v for v in chosen if v not in names]
        if missing:
            raise InputError(f"[data] views: {missing} not in the dataset's views {names}")
        picked = [index["views"][names.index(v)] for v in chosen]
        frames = np.array([[v["u"], v["v"], v["w"]] for v in picked], dtype=np.float64)
        from meshsar_builder.radar.focused import radar_from_index

        # All of the build's radar keys: a default z0_mm, aperture or reflectivity in the loss's echo
        # would compare the prediction with an echo simulated otherwise (or find no aperture centre).
        radar = radar_from_index(index)
        loss_grid = "loss_grid" in index and "loss_decimation" in index["radar"]
        grid = index["loss_grid" if loss_grid else "echo_grid"]
        return cls(
            view_names=chosen, view_index=[names.index(v) for v in chosen], frames=frames,
            fov_mm=float(index["fov_mm"]),
            positions=np.array([grid["positions_mm"][v] for v in chosen], dtype=np.float64),
            centres=radar.z0_mm * frames[:, 2], freqs=np.array(grid["frequencies_hz"], dtype=np.float64),
            radar=radar, full_radar=radar if loss_grid else None,
        )

    def echo_targets(self, batch: dict, target: str) -> torch.Tensor:
        """(B, V, M, F) complex: what the raw and profile radar losses compare with, at positions and freqs:
        target "clean", echo_clean (DESIGN section 10), or "recorded", the recorded echo on the loss grid
        (batch echo_noisy: MeshSARDataset(noisy_loss_echo=True)). A build without a loss grid holds only its
        recorded echo on the echo grid: "recorded" reads that."""
        if self.full_radar is None and target == "clean":
            raise InputError('[radar_loss] target = "clean" needs a build with a loss grid (shards format 2, '
                             'echo_clean); rebuild the data, or set target = "recorded"')
        echo = (batch["echo"] if self.full_radar is None else self._loss_grid_echo(batch, target))[:, self.view_index]
        return echo.reshape(*echo.shape[:2], -1, echo.shape[-1])  # (B, V, M, F): rows as positions

    @staticmethod
    def _loss_grid_echo(batch: dict, target: str) -> torch.Tensor:
        """The batch's echo on the loss grid for a radar loss's target: echo_clean, or echo_noisy (recorded)."""
        if target == "clean":
            return batch["echo_clean"]
        if "echo_noisy" not in batch:
            raise InputError('[radar_loss] target = "recorded": the batch has no echo_noisy')
        return batch["echo_noisy"]
