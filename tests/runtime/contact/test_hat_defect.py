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


def test_hat_defect_is_its_reference(hat_box):
    """The vectorised measurement (batched D gathers, the compiled kernel, per-vertex sums for the
    fit) against the loops: equal to rounding (the fit's normal equations against lstsq's QR on
    at most a few dozen points: 1e-9 of the largest defect)."""
    got = hat_defect(hat_box, E, NU, kernel_surface(hat_box))
    want_n, want_t = hat_defect_ref(hat_box, E, NU)
    assert np.count_nonzero(want_n) > 10  # the fit runs on most of the box's top and sides
    scale = np.abs(want_n).max()
    np.testing.assert_allclose(got.normal, want_n, rtol=0, atol=1e-9 * scale)
    np.testing.assert_allclose(got.tangential, want_t, rtol=0, atol=1e-9 * np.abs(want_t).max())
    assert hat_defect(hat_box, E, NU, kernel_surface(hat_box)) is got  # measured once per bundle and material


def test_patch_defect_is_its_reference_and_its_limits(hat_box, rng):
    """Random patches against the loops; a load on one vertex gets exactly its defect; a load
    spread evenly over a vertex and its neighbours gets far less than that vertex's share would
    alone."""
    d = hat_defect(hat_box, E, NU, kernel_surface(hat_box))
    T = np.asarray(hat_box.triangles)
    soft = np.flatnonzero(hat_box.contactable[T].all(axis=1))
    tris = rng.choice(soft, 8, replace=False)
    bary = rng.dirichlet([1, 1, 1], tris.size)
    normals = np.tile([0.0, 0.0, 1.0], (tris.size, 1))
    verts, w = patch_weights(hat_box, tris, bary, rng.uniform(5e-3, 3e-2, tris.size), normals)
    got = patch_defect(d, verts, w)
    want = patch_defect_ref(d.normal, d.tangential, T, verts, w)
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-20)

    i = int(np.flatnonzero(d.normal)[0])
    one = patch_defect(d, np.array([[i, 0]]), np.array([[1.0, 0.0]]))
    assert one[0][0] == pytest.approx(d.normal[i], rel=1e-14)
    assert one[1][0] == pytest.approx(d.tangential[i], rel=1e-14)
    ptr, nbr = d.neighbours
    ring = np.concatenate([[i], nbr[ptr[i]:ptr[i + 1]]])
    spread = patch_defect(d, ring[None, :], np.full((1, ring.size), 1.0 / ring.size))
    assert abs(spread[0][0]) < 0.5 * abs(d.normal[i]) / ring.size


def test_the_defect_can_be_left_out(hat_box):
    """``NearField(defect=False)`` is the model without it (for the studies that measure it)."""
    T = np.asarray(hat_box.triangles)
    t = np.flatnonzero(hat_box.contactable[T].all(axis=1))[:3]
    verts, w = T[t].astype(np.int64), np.full((3, 3), 1.0 / 3.0)
    off = NearField("halfspace", E, NU, defect=False).mesh_defect(hat_box, verts, w)
    on = NearField("halfspace", E, NU).mesh_defect(hat_box, verts, w)
    assert not np.any(off[0]) and not np.any(off[1])
    np.testing.assert_array_equal(on[0], patch_defect(hat_defect(hat_box, E, NU, kernel_surface(hat_box)), verts, w)[0])
