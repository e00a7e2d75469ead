"""Write the bad-input corpus, tests/data/bad/: small files that must each fail with a named error.

Run from the repository root: python tests/data/make_bad.py (the files are committed;
rerunning rewrites the same bytes).
"""

from __future__ import annotations

import gzip
from pathlib import Path

import nibabel as nib
import numpy as np

BAD = Path(__file__).resolve().parent / "bad"


def nifti_bytes(data: np.ndarray, affine=None) -> bytes:
    img = nib.Nifti1Image(data, np.eye(4) if affine is None else affine)
    return img.to_bytes()


def gz(raw: bytes) -> bytes:
    return gzip.compress(raw, mtime=0)


def without_affine(raw: bytes) -> bytes:
    """Both qform_code and sform_code 0 (bytes 252-255): only pixdim says where voxels are."""
    out = bytearray(raw)
    out[252:256] = np.array([0, 0], "<i2").tobytes()
    return bytes(out)


def with_sform(raw: bytes, sform: np.ndarray) -> bytes:
    """NIfTI-1 header: qform_code (int16) at byte 252, sform_code at 254, srow_x/y/z from 280."""
    out = bytearray(raw)
    out[252:256] = np.array([0, 1], "<i2").tobytes()
    out[280:328] = np.asarray(sform[:3], "<f4").tobytes()
    return bytes(out)


def huge_header() -> bytes:
    hdr = nib.Nifti1Header()
    hdr.set_data_shape((4000, 4000, 4000))
    hdr.set_data_dtype(np.int16)
    hdr["vox_offset"] = 352
    return hdr.binaryblock + b"\x00" * 4


def main() -> None:
    BAD.mkdir(exist_ok=True)
    labels = np.zeros((8, 8, 8), np.int16)
    labels[2:6, 2:6, 2:6] = 500
    good = nifti_bytes(labels)
    files = {
        "truncated_label.nii.gz": gz(good)[:-12],  # the gzip trailer (CRC, length) and some data cut
        "nan_affine_label.nii": with_sform(good, np.full((4, 4), np.nan)),
        "singular_affine_label.nii": with_sform(good, np.zeros((4, 4))),
        "image_2d_label.nii.gz": gz(nifti_bytes(np.full((8, 8), 500, np.int16))),
        "image_5d_label.nii.gz": gz(nifti_bytes(np.full((4, 4, 4, 2, 2), 500, np.int16))),
        "float_labels_label.nii.gz": gz(nifti_bytes(labels.astype(np.float32) + 0.25)),
        "labels_absent_label.nii.gz": gz(nifti_bytes(np.where(labels > 0, 7, 0).astype(np.int16))),
        "huge_declared_size_label.nii": huge_header(),
        # usable, with a warning (or an error where the recipe asks for it)
        "no_affine_label.nii": without_affine(good),
        "unmapped_values_label.nii.gz": gz(nifti_bytes(np.where(labels == 0, 0, np.where(np.arange(8) < 4, 500, 7)).astype(np.int16))),
        # read as labels: every value within 1e-3 of an integer
        "float_noise_label.nii.gz": gz(nifti_bytes(labels + np.random.default_rng(0).uniform(-1e-5, 1e-5, labels.shape).astype(np.float32))),
        # an intensity image next to the label maps (no _label in the name, 512 distinct values)
        "ct_image.nii.gz": gz(nifti_bytes(np.arange(512, dtype=np.int16).reshape(8, 8, 8) - 256)),
        "Info_no_NbFrame.cfg": b"ED: 1\nES: 5\nGroup: NOR\nHeight: 170.0\nWeight: 70.0\n",
    }
    verts = "\n".join(["0 0 0", "1 0 0", "nan 1 0", "0 0 1"])
    files["nan_vertices.ply"] = (
        "ply\nformat ascii 1.0\nelement vertex 4\nproperty double x\nproperty double y\nproperty double z\n"
        "element face 4\nproperty list uchar int vertex_indices\nend_header\n"
        f"{verts}\n3 0 2 1\n3 0 1 3\n3 0 3 2\n3 1 2 3\n"
    ).encode()
    source = '[[sources]]\nkind = "phantom"\nsubjects = 2\n'
    files["recipe_wrong_types.toml"] = ('name = "bad"\nseed = "zero"\n' + source).encode()
    files["recipe_unknown_key.toml"] = ('name = "bad"\n' + source + "[meshing]\nspacing_mm = 1.0\ncolour = 2\n").encode()
    files["recipe_negative_spacing.toml"] = ('name = "bad"\n' + source + "[meshing]\nspacing_mm = -1.0\n").encode()
    files["recipe_zero_samples.toml"] = ('name = "bad"\n' + source + "[ssm]\nsamples = 0\n").encode()
    files["recipe_unknown_view.toml"] = ('name = "bad"\n' + source + '[radar]\nviews = ["anterior", "dorsal"]\n').encode()
    for name, data in files.items():
        (BAD / name).write_bytes(data)


if __name__ == "__main__":
    main()
