"""Benchmarks (`meshsar bench`): radar, geometry, pipeline and trainer timings under build/bench/.

May import any subpackage.
"""

# The parts whose `--device` picks where they run; each writes its own file per device.
DEVICE_PARTS = ("radar", "trainer", "radar-throughput")


def result_name(part: str, device: str = "cpu") -> str:
    """The JSON file a part writes: radar-loss -> radar_loss.json; on a GPU (device "cuda" or "cuda:N") a
    device part's file is suffixed, radar -> radar-cuda.json, so CPU and GPU figures sit side by side."""
    kind = device.split(":")[0]
    return part.replace("-", "_") + ("" if kind == "cpu" or part not in DEVICE_PARTS else f"-{kind}") + ".json"
