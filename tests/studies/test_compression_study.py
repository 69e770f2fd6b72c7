"""Tests of studies.compression_study on the small box bundle (fixture ``box_bundle``) and the plate."""

from __future__ import annotations

import numpy as np
import pytest

from hailstorm.runtime import load
from studies.compression_study import (
    admissible,
    admissible_blocks,
    cluster_tree,
    colour_lower_bound,
    coloured_forms,
    colouring,
    compress,
    contact_vectors,
    dofs,
    force_errors,
    main,
    measure,
    peeling_solves,
    probe_error,
    random_contacts,
)

from helpers import plate_gf


@pytest.fixture(scope="module")
def box(box_bundle):
    """The box's contactable block of D and the pieces the study needs."""
    gf = load(box_bundle)
    V = np.asarray(gf.vertices, float)
    ci = np.flatnonzero(gf.contactable)
    cv = np.empty(len(ci), dtype=np.intp)
    cv[gf.column_of[ci]] = ci
    col_index = np.full(len(V), -1, dtype=np.intp)
    col_index[cv] = np.arange(len(cv))
    return {"gf": gf, "V": V, "cv": cv, "col_index": col_index, "A": np.asarray(gf.D)[dofs(cv)],
            "D": np.asarray(gf.D)}


@pytest.mark.parametrize("split", ["middle", "median"])
def test_cluster_tree_partitions_the_points(box, split):
    P = box["V"][box["cv"]]
    tree = cluster_tree(P, leaf=8, split=split)
    assert np.array_equal(np.sort(tree.perm), np.arange(len(P)))
    leaves = [tree.nodes[i] for i in tree.leaves()]
    cover = np.zeros(len(P), dtype=int)
    for lf in leaves:
        assert 1 <= lf.size <= 8
        cover[lf.start:lf.stop] += 1
    assert np.all(cover == 1)
    for node in tree.nodes:
        if node.children:
            a, b = (tree.nodes[k] for k in node.children)
            assert (a.start, a.stop, b.start, b.stop) == (node.start, a.stop, a.stop, node.stop)
        pts = P[tree.indices(tree.nodes.index(node))]
        assert np.allclose(pts.min(axis=0), node.lo) and np.allclose(pts.max(axis=0), node.hi)
    if split == "median":
        assert all(lf.size >= 4 for lf in leaves)


def test_cluster_tree_of_coincident_points_is_one_leaf():
    tree = cluster_tree(np.zeros((10, 3)), leaf=2)
    assert len(tree.nodes) == 1 and tree.nodes[0].size == 10


@pytest.mark.parametrize("eta", [1.0, 2.0, 4.0])
def test_admissible_blocks_cover_once_and_are_admissible(box, eta):
    P = box["V"][box["cv"]]
    Q = box["V"]
    rows, cols = cluster_tree(Q, leaf=6), cluster_tree(P, leaf=4)
    part = admissible_blocks(rows, cols, eta)
    assert part.far, "the box should have admissible blocks"
    cover = np.zeros((len(Q), len(P)), dtype=int)
    for i, j, _ in part.far + part.near:
        a, b = rows.nodes[i], cols.nodes[j]
        cover[a.start:a.stop, b.start:b.stop] += 1
    assert np.all(cover == 1)
    for i, j, _ in part.far:
        a, b = rows.nodes[i], cols.nodes[j]
        assert admissible(a, b, eta)
        # the real point sets satisfy it too (bounding boxes bound both diameter and distance)
        pa, pb = Q[rows.indices(i)], P[cols.indices(j)]
        dist = np.min(np.linalg.norm(pa[:, None] - pb[None], axis=2))
        diam = min(np.max(np.linalg.norm(p[:, None] - p[None], axis=2)) for p in (pa, pb))
        assert diam <= eta * dist * (1 + 1e-12)
    for i, j, _ in part.near:
        assert not rows.nodes[i].children or not cols.nodes[j].children


@pytest.mark.parametrize("tol", [0.3, 1e-1, 1e-2, 1e-3])
def test_compress_within_tol_and_measure_agrees(box, tol):
    A = box["A"]
    P = box["V"][box["cv"]]
    tree = cluster_tree(P, leaf=8)
    part = admissible_blocks(tree, tree, 1.0)
    H = compress(A, tree, tree, part, tol)
    E = A - H.to_dense()
    assert np.linalg.norm(E) <= tol * np.linalg.norm(A) * (1 + 1e-10)
    x = np.random.default_rng(0).standard_normal(A.shape[1])
    assert np.allclose(H.matvec(x), H.to_dense() @ x, rtol=1e-12, atol=1e-14 * np.abs(A).max())
    tri, w, nv = random_contacts(box["V"], box["gf"].triangles, box["gf"].contactable, 40, seed=3)
    G = contact_vectors(box["col_index"], tri, w, nv)
    (res,) = measure(A, tree, tree, part, [tol], G, G)
    assert res["frob"] == pytest.approx(np.linalg.norm(E) / np.linalg.norm(A), rel=1e-6, abs=1e-14)
    assert res["stored"] == H.stored
    assert list(res["ranks"][res["factored"]]) == list(H.ranks)
    col = np.linalg.norm(E, axis=0) / np.linalg.norm(A, axis=0)
    assert np.allclose(res["col_err"], col, rtol=1e-6, atol=1e-12)
    assert np.allclose(res["W"], G.T @ A @ G, rtol=1e-10)
    assert np.allclose(res["W_H"], G.T @ H.to_dense() @ G, rtol=1e-8, atol=1e-12 * np.abs(res["W"]).max())


def test_compress_is_exact_at_tol_zero(box):
    A = box["A"]
    tree = cluster_tree(box["V"][box["cv"]], leaf=8)
    part = admissible_blocks(tree, tree, 2.0)
    H = compress(A, tree, tree, part, 0.0)
    assert np.allclose(H.to_dense(), A, rtol=0, atol=1e-12 * np.abs(A).max())
    (res,) = measure(A, tree, tree, part, [0.0])
    assert res["frob"] < 1e-12


def test_compression_of_a_smooth_far_field_is_real():
    """On the plate (a 1/r kernel) the far blocks are of low rank: the compressed matrix is smaller."""
    gf = plate_gf(n=25)
    ci = np.flatnonzero(gf.contactable)
    A = np.asarray(gf.D)[dofs(ci)]
    tree = cluster_tree(np.asarray(gf.vertices)[ci], leaf=16)
    part = admissible_blocks(tree, tree, 2.0)
    H = compress(A, tree, tree, part, 1e-3)
    assert H.stored < 0.8 * A.size
    assert max(H.ranks) < 3 * 16
    assert np.linalg.norm(A - H.to_dense()) <= 1e-3 * np.linalg.norm(A)


def test_peeling_without_far_blocks_is_the_dense_build(box):
    """With eta = 0 nothing is admissible: every leaf meets every other, one group each, 3 c solves."""
    tree = cluster_tree(box["V"][box["cv"]], leaf=8)
    part = admissible_blocks(tree, tree, 0.0)
    assert not part.far
    pe = peeling_solves(tree, tree, part, [])
    assert pe["far_solves"] == 0 and pe["total"] == 3 * len(box["cv"])


def test_peeling_counts_grow_with_rank(box):
    tree = cluster_tree(box["V"][box["cv"]], leaf=8)
    part = admissible_blocks(tree, tree, 1.0)
    lo = peeling_solves(tree, tree, part, np.ones(len(part.far), int), oversampling=0)
    hi = peeling_solves(tree, tree, part, 5 * np.ones(len(part.far), int), oversampling=0)
    assert hi["far_solves"] == 5 * lo["far_solves"] > 0
    assert lo["near_solves"] == hi["near_solves"] <= 3 * len(box["cv"])


@pytest.mark.parametrize("sep", [0.005, 0.02, 0.05])
def test_colouring_respects_the_separation(box, sep):
    P = box["V"][box["cv"]]
    col = colouring(P, sep)
    assert col.min() == 0 and set(np.unique(col)) == set(range(col.max() + 1))
    for k in range(col.max() + 1):
        Q = P[col == k]
        d = np.linalg.norm(Q[:, None] - Q[None], axis=2) + np.eye(len(Q)) * 1e9
        assert d.min() >= sep
    assert col.max() + 1 >= colour_lower_bound(P, sep)


def test_probe_error_is_zero_with_one_vertex_per_colour(box):
    V, cv, D = box["V"], box["cv"], box["D"]
    own = np.arange(len(cv))
    pe = probe_error(D, V, V[cv], own, 0.03)
    assert np.all(pe["contamination"] == 0.0)
    assert np.all((pe["beyond"] >= 0) & (pe["beyond"] <= 1))
    big = probe_error(D, V, V[cv], own, 10.0)  # every row within reach: nothing beyond
    assert np.allclose(big["beyond"], 0.0)
    # and the near-field model is then exact wherever it reaches
    tri, w, nv = random_contacts(V, box["gf"].triangles, box["gf"].contactable, 12, seed=1)
    Gr = contact_vectors(np.arange(len(V)), tri, w, nv)
    Gc = contact_vectors(box["col_index"], tri, w, nv)
    Wt = coloured_forms(D, V, box["col_index"], V, own, 10.0, Gr, tri, w, nv)
    assert np.allclose(Wt, Gr.T @ D @ Gc, rtol=1e-12)
    assert np.allclose(force_errors(Wt, Wt, np.arange(12).reshape(3, 4)), 0.0)


def test_probe_error_sees_contamination(box):
    V, cv, D = box["V"], box["cv"], box["D"]
    col = colouring(V[cv], 0.02)
    assert col.max() + 1 < len(cv)
    pe = probe_error(D, V, V[cv], col, 0.01)
    assert pe["contamination"].max() > 0


def test_main_prints_the_tables(box_bundle, tmp_path, capsys):
    out = tmp_path / "compression.txt"
    main(["--gf", str(box_bundle), "--leaf", "8", "--eta", "1,2", "--tols", "1e-2,1e-3", "--probes", "30",
          "--sets", "5", "--set-size", "4", "--pad", "0.01", "--separations", "1,2", "--out", str(out)])
    text = out.read_text()
    assert text == capsys.readouterr().out
    first, second = text.splitlines()[:2]
    assert first.startswith("$ python -m studies.compression_study --gf ")
    assert "UTC" in second and "git" in second and "load average" in second
    for head in ("## 1. H-matrix", "## 2. Solves", "## 3. Several", "## Run time"):
        assert head in text
