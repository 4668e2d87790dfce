"""Polygons with holes from the nesting (core.nesting, result.polygons / to_shapely) and the
GeoJSON exporter."""
from __future__ import annotations

import json

import numpy as np
import pytest

import torch_isc
from torch_isc.cli import EXAMPLE_PATH
from torch_isc.core.nesting import polygon_nesting, polygons_with_holes, signed_area
from torch_isc.io import geojson_dict, read_points


def _sq(a, b, x0=0.0):
    return np.array([[a + x0, a], [b + x0, a], [b + x0, b], [a + x0, b]], float)


def test_nesting_depth_parent_and_rings():
    # two outlines side by side; the first holds a hole with an island holding a hole
    polys = [_sq(0, 10), _sq(1, 9), _sq(2, 8), _sq(3, 7), _sq(0, 4, x0=20), _sq(1, 2, x0=20), _sq(2.5, 3.5, x0=20)]
    parent, depth = polygon_nesting(polys)
    assert depth.tolist() == [0, 1, 2, 3, 0, 1, 1] and parent.tolist() == [-1, 0, 1, 2, -1, 4, 4]
    assert polygons_with_holes(polys) == [(0, [1]), (2, [3]), (4, [5, 6])]
    # the order of the list does not matter
    perm = [6, 3, 0, 5, 2, 4, 1]
    got = polygons_with_holes([polys[i] for i in perm])
    assert sorted((perm[e], sorted(perm[h] for h in hs)) for e, hs in got) == [(0, [1]), (2, [3]), (4, [5, 6])]


@pytest.fixture(scope="module")
def nested():
    return torch_isc.reconstruct(read_points(EXAMPLE_PATH), name="nested")


def test_to_shapely_follows_the_hierarchy(nested):
    shapely = pytest.importorskip("shapely")
    polys = nested.polygons()
    assert nested.num_closed == 4
    assert sorted(len(h) for _, h in polys) == [0, 2]               # an outline with two holes, an island
    for ext, holes in polys:
        assert signed_area(ext) > 0 and all(signed_area(h) < 0 for h in holes)
    mp = nested.to_shapely()
    assert isinstance(mp, shapely.MultiPolygon) and mp.is_valid and len(mp.geoms) == 2
    rings = [p["points"].double().numpy() for p in nested.polylines]
    _, depth = polygon_nesting(rings)
    assert sorted(depth.tolist()) == [0, 1, 1, 2]
    expected = sum((-1) ** int(d) * abs(signed_area(r)) for r, d in zip(rings, depth))
    assert np.isclose(mp.area, expected, rtol=1e-12)                # outline - holes + island
    # a point in a hole is outside the region, one in the island inside, as the curve says
    import torch
    grid = torch.stack(torch.meshgrid(torch.linspace(*mp.bounds[0::2], 40, dtype=torch.float64),
                                      torch.linspace(*mp.bounds[1::2], 40, dtype=torch.float64),
                                      indexing="ij"), -1).reshape(-1, 2)
    inside = nested.curve.inside(grid)
    got = shapely.contains_xy(mp, grid[:, 0].numpy(), grid[:, 1].numpy())
    assert (got == inside.numpy()).mean() > 0.99


def test_geojson_is_the_same_regions(nested, tmp_path):
    shapely = pytest.importorskip("shapely")
    from shapely.geometry import shape

    (path,) = torch_isc.io.export(nested, tmp_path / "n", ["geojson"])
    d = json.loads(path.read_text())
    assert d["type"] == "FeatureCollection" and len(d["features"]) == 1
    f = d["features"][0]
    assert f["properties"]["name"] == "nested" and f["properties"]["num_closed"] == 4
    rings = [r for poly in f["geometry"]["coordinates"] for r in poly]
    assert all(r[0] == r[-1] for r in rings)                        # closed rings
    assert shape(f["geometry"]).equals(nested.to_shapely())
    assert path.read_bytes() == (tmp_path / "n.geojson").read_bytes()
    assert geojson_dict([nested, nested])["features"][1] == f


def test_no_curve_is_an_empty_multipolygon():
    res = torch_isc.reconstruct(np.array([[0.0, 0], [1, 0], [2, 0], [3, 0]]))
    assert res.num_components == 0 and res.polygons() == []
    assert geojson_dict(res)["features"][0]["geometry"] == {"type": "MultiPolygon", "coordinates": []}
    shapely = pytest.importorskip("shapely")
    assert res.to_shapely().is_empty
