"""The io registries: every exporter encodes, every loader suffix loads, unknown formats and
missing context are rejected before anything is written."""
from __future__ import annotations

import io
import os

import cv2
import numpy as np
import pytest
import torch

from torch_isc import reconstruct
from torch_isc.io import (EXPORTERS, LOADERS, ExportContext, chosen_formats, export, formats_needing, loader_for,
                          read_points)

MAGIC = {"json": b"{\n", "npz": b"PK", "svg": b"<?xml", "png": b"\x89PNG", "contours.npz": b"PK",
         "geojson": b'{"type":"FeatureCollection"', "overlay.png": b"\x89PNG"}


@pytest.fixture(scope="module")
def result():
    t = torch.linspace(0, 2 * np.pi, 80, dtype=torch.float64)[:-1]
    return reconstruct(torch.stack([20 + 8 * t.cos(), 20 + 8 * t.sin()], 1), name="ring")


def test_every_exporter_encodes_and_export_writes_the_same_bytes(result, tmp_path):
    assert set(MAGIC) == set(EXPORTERS)
    ctx = ExportContext(y_down=True, image=np.zeros((40, 40), np.float32))
    for name, exporter in EXPORTERS.items():
        fh = io.BytesIO()
        exporter.encode(result, fh, ctx)
        assert fh.getvalue().startswith(MAGIC[name]), name
        (path,) = export(result, tmp_path / "r", [name], context=ctx)
        assert path.name == f"r.{name}" and path.read_bytes() == fh.getvalue(), name
    assert sorted(os.listdir(tmp_path)) == sorted(f"r.{n}" for n in EXPORTERS)   # no temporary file left


def test_formats_that_need_context(result, tmp_path):
    assert chosen_formats() == ["json", "npz", "svg", "png", "contours.npz", "geojson"]
    assert formats_needing({"image"}) == ["overlay.png"] and formats_needing(()) == []
    with pytest.raises(ValueError, match="'overlay.png' needs the image"):
        export(result, tmp_path / "r", ["json", "overlay.png"])
    with pytest.raises(ValueError, match="unknown output format 'obj'"):
        export(result, tmp_path / "r", ["json", "obj"])
    assert os.listdir(tmp_path) == []


def test_a_loader_per_suffix(tmp_path):
    pts = np.array([[0.0, 1.0], [2.5, -3.0], [4.0, 5.0]])
    img = np.zeros((6, 8), np.uint8)
    img[2:4, 3:6] = 255
    for suffix, loader in LOADERS.items():
        path = tmp_path / f"f{suffix}"
        if loader.kind == "points":
            if suffix == ".npy":
                np.save(path, pts)
            else:
                sep = "," if suffix == ".csv" else " "
                path.write_text("x" + sep + "y\n" + "\n".join(sep.join(f"{v:.17g}" for v in p) for p in pts) + "\n")
            got = loader.load(path)
            assert got.dtype == np.float64 and np.array_equal(got, pts), suffix
        else:
            if suffix == ".gif":                                  # OpenCV's GIF encoder fails on gray
                Image = pytest.importorskip("PIL.Image")
                Image.fromarray(img).save(path)
            else:                                                 # WebP: quality > 100 is lossless
                assert cv2.imwrite(str(path), img, [cv2.IMWRITE_WEBP_QUALITY, 101] if suffix == ".webp" else []), suffix
            got = loader.load(path)
            assert got.dtype == np.float32 and got.shape == img.shape, suffix
            if suffix not in (".jpg", ".jpeg"):                  # lossy
                assert np.array_equal(got, img / 255.0), suffix
        assert loader_for(path) is loader
    # any other suffix is read as a point file, and a .npy under another name as .npy
    np.save(tmp_path / "g.npy", pts)
    os.replace(tmp_path / "g.npy", tmp_path / "g.dat")
    assert loader_for(tmp_path / "g.dat").kind == "points" and np.array_equal(read_points(tmp_path / "g.dat"), pts)


@pytest.mark.parametrize("module,forbidden", [
    ("torch_isc.pipeline.loop", ("torch_isc.images", "torch_isc.io", "torch_isc.runner", "torch_isc.cli")),
    ("torch_isc.images", ("torch_isc.io", "torch_isc.runner", "torch_isc.cli")),
    ("torch_isc.io", ("torch_isc.runner", "torch_isc.cli")),
    ("torch_isc.runner", ("torch_isc.cli", "torch_isc.dataset")),
    ("torch_isc.dataset", ("torch_isc.cli",)),
    ("torch_isc", ("torch_isc.images", "torch_isc.io", "torch_isc.runner", "torch_isc.cli")),
])
def test_layers_import_only_below(module, forbidden):
    """core <- pipeline <- images <- io <- runner <- dataset <- cli: no layer loads one above it."""
    import subprocess
    import sys

    code = f"import sys, {module}; print(sorted(m for m in sys.modules if m.startswith('torch_isc')))"
    loaded = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                            cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__)))).stdout
    assert not [m for m in forbidden if f"'{m}'" in loaded or f"'{m}." in loaded], loaded


def test_core_imports_nothing_above_it():
    """core/ is read by everything: its modules import no pipeline, image, file or CLI code
    (checked on the source, since importing any submodule runs the package's __init__)."""
    import re
    core = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "torch_isc", "core")
    for name in sorted(os.listdir(core)):
        if name.endswith(".py"):
            text = open(os.path.join(core, name)).read()
            bad = re.findall(r"^\s*(?:from|import) torch_isc\.(pipeline|images|io|runner|cli)\b", text, re.M)
            assert not bad, (name, bad)
