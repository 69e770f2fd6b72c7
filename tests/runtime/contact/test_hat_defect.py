"""D's own error at the scale of one hat load (hailstorm.runtime.contact.hat_defect).

References: the plain statements in ``tests/reference/near_field_ref.py`` (loops, one pair and
one patch at a time), the definition's own limits (a load on one vertex gets all of its defect,
a spread one next to none), and what it is for: on a graded block of foam, a sphere's force no
longer depends on where on the mesh it lands (in ``test_near_field.py``).
"""

from __future__ import annotations

import numpy as np
import pytest

import hailstorm.runtime
from hailstorm.precompute import build_bundle
from hailstorm.runtime.contact.hat_defect import hat_defect, patch_defect, vertex_neighbours
from hailstorm.runtime.contact.near_field import NearField, kernel_surface
from hailstorm.runtime.contact.weights import patch_weights
from reference.near_field_ref import hat_defect_ref, patch_defect_ref

E, NU = 1.0e6, 0.3


@pytest.fixture(scope="module")
def hat_box(tmp_path_factory, small_box):
    """:func:`small_box` (20 mm elements) with P2 columns answering hat loads."""
    out = tmp_path_factory.mktemp("hatbox") / "box"
    return hailstorm.runtime.load(build_bundle(out, mesh=small_box, order=2, young=E, poisson=NU, load="hat"))


def test_vertex_neighbours_are_the_surface_edges(hat_box):
    T = np.asarray(hat_box.triangles)
    ptr, nbr = vertex_neighbours(T, hat_box.n_vertices)
    want: dict[int, set[int]] = {}
    for t in T:
        for a, b in ((0, 1), (1, 2), (2, 0)):
            want.setdefault(int(t[a]), set()).add(int(t[b]))
            want.setdefault(int(t[b]), set()).add(int(t[a]))
    for v in range(hat_box.n_vertices):
        assert nbr[ptr[v]:ptr[v + 1]].tolist() == sorted(want.get(v, ()))


def near_dict(d) -> dict[tuple[int, int], tuple[float, float]]:
    """A :class:`HatDefect`'s near pairs as the references state them."""
    n = d.normal.size
    return {(int(k // n), int(k % n)): (float(a), float(b)) for k, a, b in zip(d.keys, d.near_normal, d.near_tangential)}


def test_hat_defect_is_its_reference(hat_box):
    """The vectorised measurement (batched D gathers, the compiled kernel, per-vertex sums for the
    fit) against the loops: the same near pairs, equal to rounding (the fit's normal equations
    against lstsq's QR on a few dozen points: 1e-9 of the largest defect)."""
    got = hat_defect(hat_box, E, NU, kernel_surface(hat_box))
    want = hat_defect_ref(hat_box, E, NU)
    have = near_dict(got)
    assert sum(i == j for i, j in want) > 10  # the fit runs on most of the box's top and sides
    assert set(have) == set(want)
    scale_n = max(abs(v[0]) for v in want.values())
    scale_t = max(abs(v[1]) for v in want.values())
    for key, (dn, dt) in want.items():
        assert have[key][0] == pytest.approx(dn, abs=1e-9 * scale_n)
        assert have[key][1] == pytest.approx(dt, abs=1e-9 * scale_t)
    for (i, j), (dn, dt) in want.items():
        if i == j:
            assert got.normal[i] == pytest.approx(-dn, abs=1e-9 * scale_n)
    assert hat_defect(hat_box, E, NU, kernel_surface(hat_box)) is got  # measured once per bundle and kernel


def test_the_defect_is_where_the_elements_put_it(hat_box):
    """The box (20 mm elements, P2, hat loads): each vertex's own displacement short (``delta_ii < 0``)
    and its edge neighbours' long (``delta_ij > 0``); the pad's own figures are in
    ``tests/studies/test_layer_pad.py``."""
    d = near_dict(hat_defect(hat_box, E, NU, kernel_surface(hat_box)))
    diag = {i: v[0] for (i, j), v in d.items() if i == j}
    ring: dict[int, float] = {}
    for (i, j), v in d.items():
        if i != j:
            ring[i] = ring.get(i, 0.0) + v[0]
    assert np.median([diag[i] for i in diag]) < 0
    assert np.median([ring[i] for i in diag]) > 0


def test_patch_defect_is_its_reference_and_its_limits(hat_box, rng):
    """Random patches against the loops; a load on one vertex gets exactly its defect; a load
    spread evenly over a vertex and its ring gets less than that vertex's would alone."""
    d = hat_defect(hat_box, E, NU, kernel_surface(hat_box))
    T = np.asarray(hat_box.triangles)
    soft = np.flatnonzero(hat_box.contactable[T].all(axis=1))
    tris = rng.choice(soft, 8, replace=False)
    bary = rng.dirichlet([1, 1, 1], tris.size)
    normals = np.tile([0.0, 0.0, 1.0], (tris.size, 1))
    verts, w = patch_weights(hat_box, tris, bary, rng.uniform(5e-3, 3e-2, tris.size), normals)
    got = patch_defect(d, verts, w)
    want = patch_defect_ref(near_dict(d), verts, w)
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-20)

    i = int(np.flatnonzero(d.normal)[0])
    one = patch_defect(d, np.array([[i, 0]]), np.array([[1.0, 0.0]]))
    assert one[0][0] == pytest.approx(d.normal[i], rel=1e-14)
    assert one[1][0] == pytest.approx(d.tangential[i], rel=1e-14)
    ptr, nbr = vertex_neighbours(T, hat_box.n_vertices)
    ring = np.concatenate([[i], nbr[ptr[i]:ptr[i + 1]]])
    spread = patch_defect(d, ring[None, :], np.full((1, ring.size), 1.0 / ring.size))
    assert abs(spread[0][0]) < 0.5 * abs(d.normal[i])


def test_the_defect_can_be_left_out(hat_box):
    """``NearField(defect=False)`` is the model without it (for the studies that measure it)."""
    T = np.asarray(hat_box.triangles)
    t = np.flatnonzero(hat_box.contactable[T].all(axis=1))[:3]
    verts, w = T[t].astype(np.int64), np.full((3, 3), 1.0 / 3.0)
    off = NearField("halfspace", E, NU, defect=False).mesh_defect(hat_box, verts, w)
    on = NearField("halfspace", E, NU).mesh_defect(hat_box, verts, w)
    assert not np.any(off[0]) and not np.any(off[1])
    np.testing.assert_array_equal(on[0], patch_defect(hat_defect(hat_box, E, NU, kernel_surface(hat_box)), verts, w)[0])


def test_the_defect_is_cached_on_disk_exactly_and_per_material(hat_box, tmp_path, monkeypatch):
    """Measured once per bundle and material: a second load of the bundle reads the file (the
    same numbers, bit for bit), another material or a damaged file measures anew."""
    monkeypatch.setenv("HAILSTORM_CACHE", str(tmp_path / "cache"))
    fresh_box = hailstorm.runtime.load(hat_box.path)  # not the module's object: its defect may be in memory
    first = hat_defect(fresh_box, E, NU, kernel_surface(fresh_box))
    files = sorted((tmp_path / "cache" / "hat_defect").glob("*.npz"))
    assert len(files) == 1
    again = hailstorm.runtime.load(hat_box.path)  # a new object: nothing in memory
    read = hat_defect(again, E, NU, kernel_surface(again))
    for name in ("keys", "near_normal", "near_tangential", "normal", "tangential"):
        np.testing.assert_array_equal(getattr(read, name), getattr(first, name))
    hat_defect(again, 2 * E, NU, kernel_surface(again))  # another material: its own file
    assert len(list((tmp_path / "cache" / "hat_defect").glob("*.npz"))) == 2
    files[0].write_bytes(b"not a defect")
    third = hailstorm.runtime.load(hat_box.path)
    fresh = hat_defect(third, E, NU, kernel_surface(third))  # measured again, and rewritten
    np.testing.assert_array_equal(fresh.near_normal, first.near_normal)
    assert np.load(files[0])["keys"].shape == first.keys.shape
