"""The multigrid hierarchy's structure, built once per model with numpy: smoothed aggregation.

Level 0 is the particles (the matrix-free operator of Eq. 15, 3x3 blocks); every
coarser level has one node per aggregate of the level above and 6 unknowns per
node (the 3 translations and 3 rotations of the aggregate: the rigid motions a
spring network resists least, its near-nullspace). Built here, once:

* the strength graph of each level: j is strong for i when the block of A at rest
  (springs unstretched) satisfies ||A_ij|| >= THETA sqrt(||A_ii|| ||A_jj||)
  (Frobenius norms): weak couplings (the cloth's bending springs) do not glue
  aggregates together;
* aggregates by greedy standard aggregation (Vanek, Mandel and Brezina 1996):
  a node whose strong neighbours are all free starts an aggregate with them; every
  other node joins the aggregate it is most strongly connected to; nodes without
  strong neighbours (and pinned particles) belong to none;
* the member lists of the aggregates, for the tentative prolongation T that the
  kernels build every step: per aggregate, an orthonormal basis (modified
  Gram-Schmidt, a thin QR) of its members' near-nullspace vectors at the current
  positions, so T^T T = I; R of the QR is the coarse level's near-nullspace.
  Rotations are taken about each aggregate's centre (the mean of its members'),
  and a coarse node's candidates are shifted to its aggregate's centre before the
  next QR: all members must describe the same rigid motions (``rigid_modes``,
  ``coarse_modes`` and ``tentative`` here are the kernels' numpy reference);
* the patterns of what the per-step kernels (``kernels/multigrid.py``) fill in:
  the smoothed prolongation P = (I - omega/rho D^-1 A) T (row i: the aggregates of i
  and of its neighbours), A P and the Galerkin coarse operator P^T A P, with the
  index lists that say which block products go where;
* level 0's weak couplings filtered (``FILTER_WEAK``, ``filter_fine``): P is smoothed
  with A_s, A without its weak couplings (springs and all: A_s,ii = A_ii + sum of the
  weak A_ij), so row i of P holds the aggregates of i and of its strong neighbours
  only; the Galerkin product takes A' = A_s plus the weak couplings that add no block
  to P^T A_s P. On the cloth the weak couplings are the bending springs: at 128 x 128
  level 1 has 14,280 off-diagonal blocks instead of 35,108, P 44,945 blocks instead
  of 66,448, and a third of the bending couplings (those that would widen level 1)
  are left out. Left out entirely (A_s for both), the coarse levels were as sparse,
  but CG took up to 1.5x the iterations at ks 1e6 (the coarse correction overshoots
  the modes the bending springs stiffen); with A' it takes the unfiltered counts
  (``benchmarks/multigrid_cycles.py``, variant "all couplings").

Values change every step (K and D follow the positions, and so do the rotations
that K resists least): the kernels recompute T, P, A P and P^T A P in these
patterns (rotations about the initial geometry instead let the iteration count
grow as the cloth moves). Pinned particles have no aggregate and zero rows of P:
the coarse levels see the free particles only.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

THETA = 0.08           # strength threshold on level 0 (drops the cloth's bending springs)
COARSE_THETA = 0.0     # on coarser levels, whose summed coupling norms say less: every coupling
MAX_COARSE = 600       # unknowns of the coarsest level (solved by dense Cholesky), at most
MAX_LEVELS = 12
COARSE_BS = 6          # unknowns per coarse node: 3 translations, 3 rotations
FILTER_WEAK = True     # level 0's weak couplings are left out of P and of the coarse operators
DROP = 1e-4            # a candidate whose part orthogonal to the previous ones is below DROP times
                       # its norm is dropped (a zero column of T: the rotation about the axis of
                       # collinear members); its coarse unknown is then idle


@dataclass
class Transfer:
    """One level's prolongation structure, fine nodes ``nf`` -> coarse nodes ``nc``.

    ``agg`` (nf,): aggregate of each fine node (-1: none); ``member_rows`` (nc+1,),
    ``members``: the fine nodes of each aggregate (CSR, ascending); ``p_rows``
    (nf+1,), ``p_cols`` (np,): P's pattern (CSR by fine node; columns are coarse
    nodes); ``tent_slot`` (nf,): the block of P row i holding T's block (-1).
    """

    nf: int
    nc: int
    bf: int
    agg: np.ndarray
    member_rows: np.ndarray
    members: np.ndarray
    p_rows: np.ndarray
    p_cols: np.ndarray
    tent_slot: np.ndarray


def strength_graph(n, pairs, weights, diag_norm, theta=THETA):
    """Symmetric strong neighbours (CSR: rows (n+1,), cols, weights) of n nodes from
    undirected couplings ``pairs`` (k, 2) of Frobenius norm ``weights``; parallel
    couplings add up."""
    keys = np.minimum(pairs[:, 0], pairs[:, 1]) * n + np.maximum(pairs[:, 0], pairs[:, 1])
    keys, inverse = np.unique(keys, return_inverse=True)
    w = np.bincount(inverse, weights=weights)
    i, j = keys // n, keys % n
    strong = (i != j) & (w > 0) & (w >= theta * np.sqrt(diag_norm[i] * diag_norm[j]))
    i, j, w = i[strong], j[strong], w[strong]
    rows = np.concatenate([i, j])
    cols = np.concatenate([j, i])
    ws = np.concatenate([w, w])
    order = np.lexsort((cols, rows))
    offsets = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(np.bincount(rows, minlength=n), out=offsets[1:])
    return offsets, cols[order], ws[order]


def aggregate(offsets, cols, weights):
    """Greedy standard aggregation (see the module docstring), deterministic in node
    order. Returns (agg (n,) with aggregate ids or -1, number of aggregates)."""
    n = len(offsets) - 1
    agg = [-1] * n
    count = 0
    offs, nbrs = offsets.tolist(), cols.tolist()
    for i in range(n):
        if agg[i] >= 0 or offs[i] == offs[i + 1]:
            continue
        neighbours = nbrs[offs[i]:offs[i + 1]]
        if all(agg[j] < 0 for j in neighbours):
            agg[i] = count
            for j in neighbours:
                agg[j] = count
            count += 1
    first = np.array(agg)
    out = first.copy()
    for i in np.flatnonzero(first < 0):
        lo, hi = offsets[i], offsets[i + 1]
        if lo == hi:
            continue
        nb, w = cols[lo:hi], weights[lo:hi]
        ok = first[nb] >= 0
        if ok.any():
            out[i] = first[nb[ok][np.argmax(w[ok])]]
    return out, count


def centres(points, agg, count):
    """Each aggregate's centre (count, 3): the mean of its members' ``points`` (n, 3)."""
    members = agg >= 0
    total = np.zeros((count, 3))
    np.add.at(total, agg[members], points[members])
    return total / np.maximum(np.bincount(agg[members], minlength=count), 1)[:, None]


def shift(d):
    """S(d) (..., 6, 6): candidates given as translations and rotations about a point c,
    times S(d), are the same motions with the rotations about c - d: rotation k about
    c - d is rotation k about c plus the translation e_k x d."""
    out = np.broadcast_to(np.eye(6), d.shape[:-1] + (6, 6)).copy()
    for k in range(3):
        axis = np.zeros(3)
        axis[k] = 1.0
        out[..., :3, 3 + k] = np.cross(axis, d)
    return out


def rigid_modes(x, agg, count):
    """Level 0's near-nullspace (n, 3, 6) and the aggregates' centres (count, 3):
    translations and rotations about each particle's aggregate centre (zero for
    particles without aggregate)."""
    centre = centres(x, agg, count)
    members = agg >= 0
    modes = np.zeros((len(x), 3, 6))
    modes[members] = shift(x[members] - centre[agg[members]])[:, :3, :]
    return modes, centre


def coarse_modes(candidates, node_centres, agg, count):
    """A coarse level's near-nullspace for its aggregation (n, 6, 6) and the next
    centres: each node's candidates (R of its QR, rotations about its own centre)
    re-expressed with rotations about its aggregate's centre."""
    centre = centres(node_centres, agg, count)
    members = agg >= 0
    modes = np.zeros_like(candidates)
    modes[members] = candidates[members] @ shift(node_centres[members] - centre[agg[members]])
    return modes, centre


def tentative(agg, count, candidates, drop=DROP):
    """T's blocks (n, bf, 6) and the coarse candidates (count, 6, 6): per aggregate, modified
    Gram-Schmidt on its members' stacked candidate blocks (in member order), a thin QR
    B = Q R with R's diagonal >= 0; a column whose remainder is at most ``drop`` times
    its norm is dropped (zero in Q and on R's diagonal). The numpy reference of the
    kernels' ``tentative0``/``tentativec``."""
    n, bf, k = candidates.shape
    members = np.flatnonzero(agg >= 0)
    order = members[np.argsort(agg[members], kind="stable")]
    sizes = np.bincount(agg[members], minlength=count)
    starts = np.concatenate([[0], np.cumsum(sizes)])
    blocks = np.zeros((n, bf, k))
    coarse = np.zeros((count, k, k))
    for size in np.unique(sizes[sizes > 0]):
        ids = np.flatnonzero(sizes == size)
        nodes = order[starts[ids][:, None] + np.arange(size)[None, :]]
        q = candidates[nodes].reshape(len(ids), size * bf, k).copy()
        r = np.zeros((len(ids), k, k))
        for j in range(k):
            norm0 = np.linalg.norm(q[:, :, j], axis=1)
            for p in range(j):
                d = np.sum(q[:, :, p] * q[:, :, j], axis=1)
                r[:, p, j] = d
                q[:, :, j] -= d[:, None] * q[:, :, p]
            norm = np.linalg.norm(q[:, :, j], axis=1)
            live = norm > drop * norm0
            q[:, :, j] = np.where(live[:, None], q[:, :, j] / np.where(live, norm, 1.0)[:, None], 0.0)
            r[:, j, j] = np.where(live, norm, 0.0)
        blocks[nodes.ravel()] = q.reshape(len(ids) * size, bf, k)
        coarse[ids] = r
    return blocks, coarse


def csr_union(n, rows, cols):
    """The sorted unique (row, col) pairs of ``rows``/``cols`` as CSR (offsets, cols),
    and for every input pair its index in that pattern."""
    width = int(cols.max()) + 1 if len(cols) else 1
    keys = rows.astype(np.int64) * width + cols
    unique, inverse = np.unique(keys, return_inverse=True)
    offsets = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(np.bincount(unique // width, minlength=n), out=offsets[1:])
    return offsets, unique % width, inverse


def transfer(nf, bf, agg, count, op_rows, op_cols):
    """The prolongation structure of one level: the aggregates' member lists, and P's
    pattern, whose row i holds the aggregates of i and of its operator neighbours
    ``op_cols[op_rows[i]:op_rows[i+1]]``."""
    owner = np.repeat(np.arange(nf), np.diff(op_rows))
    rows = np.concatenate([np.arange(nf), owner])
    cols = np.concatenate([agg, agg[op_cols]])
    keep = cols >= 0
    p_rows, p_cols, index = csr_union(nf, rows[keep], cols[keep])
    tent_slot = np.full(nf, -1, dtype=np.int64)
    has = agg >= 0
    tent_slot[has] = index[:int(has.sum())]  # the kept self pairs come first, in node order
    members = np.flatnonzero(has)
    members = members[np.argsort(agg[members], kind="stable")]
    return Transfer(nf, count, bf, agg, _csr_offsets(count, agg[members]), members, p_rows, p_cols, tent_slot)


@dataclass
class Level:
    """Structure of one level ``l`` and its transfer to level l + 1 (all index arrays int64).

    Operator pattern: node i's off-diagonal entries ``off_cols[off_rows[i]:off_rows[i+1]]``
    (level 0: the adjacency entries of ``device.adjacency``, one per spring end;
    coarse levels: the Galerkin pattern). ``transfer``: P's structure (None on the
    coarsest level). Per-step index lists (for ``kernels/multigrid.py``):

    * ``entry_slot`` (off,): the P block of row i that entry (i, j)'s A_ij T_j
      lands in (P's block of agg(j)), or -1 when j has no aggregate;
    * A P: ``ap_rows``/``ap_cols``: its pattern (CSR by fine node); ``apt_rows``
      (nf+1,) and ``apt_entry`` (-1: the diagonal block, else an off-diagonal entry),
      ``apt_p``, ``apt_ap``: per row, the products A_ij P_jJ and where they go;
    * P^T A P, the upper triangle (I <= J) only (the operator is symmetric):
      ``c_off_rows``/``c_off_cols`` its off-diagonal pattern (both triangles);
      ``gal_rows`` (k+1,): for each coarse block of ``gal_block`` (the diagonal block
      of node I as -1 - I, an off-diagonal entry as its index) the pairs
      ``gal_p``, ``gal_ap`` whose products P_iI^T (AP)_iJ sum to it;
      ``c_mirror`` (c_off,): the index of each off-diagonal entry's transpose;
    * restriction P^T: ``pt_rows`` (nc+1,), ``pt_block``, ``pt_fine``: per coarse node,
      P's blocks in its column and their fine nodes;
    * level 0 only: ``entry`` (off,), the adjacency entry of each off-diagonal entry
      (the couplings kept, ``filter_fine``), and ``smooth`` (off,) bool, those that
      smooth P (None: all).
    """

    n: int
    bs: int
    off_rows: np.ndarray
    off_cols: np.ndarray
    transfer: Transfer | None = None
    entry_slot: np.ndarray | None = None
    ap_rows: np.ndarray | None = None
    ap_cols: np.ndarray | None = None
    apt_rows: np.ndarray | None = None
    apt_entry: np.ndarray | None = None
    apt_p: np.ndarray | None = None
    apt_ap: np.ndarray | None = None
    gal_rows: np.ndarray | None = None
    gal_block: np.ndarray | None = None
    gal_p: np.ndarray | None = None
    gal_ap: np.ndarray | None = None
    c_mirror: np.ndarray | None = None
    pt_rows: np.ndarray | None = None
    pt_block: np.ndarray | None = None
    pt_fine: np.ndarray | None = None
    entry: np.ndarray | None = None
    smooth: np.ndarray | None = None


def _csr_offsets(n, rows):
    offsets = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(np.bincount(rows, minlength=n), out=offsets[1:])
    return offsets


def link(level):
    """Fill ``level``'s index lists from its operator pattern and transfer; returns the
    next level's off-diagonal pattern (off_rows, off_cols)."""
    t = level.transfer
    nf, nc = t.nf, t.nc
    off_owner = np.repeat(np.arange(nf), np.diff(level.off_rows))
    # smoothing: the P block of row i for agg(j) of each off-diagonal entry
    agg_j = t.agg[level.off_cols]
    slot = np.full(len(agg_j), -1, dtype=np.int64)
    ok = agg_j >= 0
    if level.smooth is not None:
        ok &= level.smooth
    slot[ok] = _find(t.p_rows, t.p_cols, off_owner[ok], agg_j[ok])
    level.entry_slot = slot
    owner, entry, p_block, (ap_rows, ap_cols, ap_index) = _ap_pattern(level)
    level.ap_rows, level.ap_cols = ap_rows, ap_cols
    level.apt_rows = _csr_offsets(nf, owner)
    level.apt_entry, level.apt_p, level.apt_ap = entry, p_block, ap_index
    p_of, ap_of, big_i, big_j = _galerkin_pairs(t, ap_rows, ap_cols)
    # the next level's off-diagonal pattern (both triangles) and its entry of each pair
    pairs, order, c_off_rows, c_off_cols = _next_pattern(big_i, big_j, nc)
    offd = big_i != big_j
    position = np.empty(len(order), dtype=np.int64)
    position[order] = np.arange(len(order))
    upper_entry = position[:len(pairs)]                                # entry (I, J), I < J
    lower_entry = position[len(pairs):]                                # entry (J, I)
    mirror = np.empty(len(order), dtype=np.int64)
    mirror[upper_entry] = lower_entry
    mirror[lower_entry] = upper_entry
    level.c_mirror = mirror
    block = -1 - big_i
    block[offd] = upper_entry[np.searchsorted(pairs, big_i[offd] * nc + big_j[offd])]
    order = np.argsort(block, kind="stable")
    block, level.gal_p, level.gal_ap = block[order], p_of[order], ap_of[order]
    targets, starts = np.unique(block, return_index=True)
    level.gal_block = targets
    level.gal_rows = np.concatenate([starts, [len(block)]]).astype(np.int64)
    # restriction: P^T by coarse node
    p_owner = np.repeat(np.arange(nf), np.diff(t.p_rows))
    order = np.argsort(t.p_cols, kind="stable")
    level.pt_rows = _csr_offsets(nc, t.p_cols)
    level.pt_block, level.pt_fine = order, p_owner[order]
    return c_off_rows, c_off_cols


def _ap_pattern(level):
    """A P's products, row i getting A_ii P_i. and A_ij P_j. for every entry: per product
    (in row order) its row, source entry (-1: the diagonal block) and P block; and A P's
    pattern from ``csr_union`` (offsets, cols, each product's block)."""
    t, nf = level.transfer, level.transfer.nf
    off_owner = np.repeat(np.arange(nf), np.diff(level.off_rows))
    src_node = np.concatenate([np.arange(nf), level.off_cols])          # whose P row
    src_entry = np.concatenate([np.full(nf, -1), np.arange(len(level.off_cols))])
    src_owner = np.concatenate([np.arange(nf), off_owner])
    which, p_block = _ranges(t.p_rows[src_node], np.diff(t.p_rows)[src_node])
    order = np.argsort(src_owner[which], kind="stable")
    owner, entry, p_block = src_owner[which][order], src_entry[which][order], p_block[order]
    return owner, entry, p_block, csr_union(nf, owner, t.p_cols[p_block])


def _galerkin_pairs(t, ap_rows, ap_cols):
    """P^T A P's products: the pairs (P block (i, I), AP block (i, J)) of every fine row
    i with I <= J, as (P block, AP block, I, J)."""
    _, p_of, ap_of = _cartesian(t.p_rows[:-1], np.diff(t.p_rows), ap_rows[:-1], np.diff(ap_rows))
    big_i, big_j = t.p_cols[p_of], ap_cols[ap_of]
    upper = big_i <= big_j
    return p_of[upper], ap_of[upper], big_i[upper], big_j[upper]


def coarse_pattern(level):
    """The next level's off-diagonal pattern (offsets, cols; both triangles) that
    ``link`` returns, without filling ``level``'s index lists."""
    _, _, _, (ap_rows, ap_cols, _) = _ap_pattern(level)
    _, _, big_i, big_j = _galerkin_pairs(level.transfer, ap_rows, ap_cols)
    return _next_pattern(big_i, big_j, level.transfer.nc)[2:]


def _next_pattern(big_i, big_j, nc):
    """From P^T A P's pairs (I, J), I <= J: the off-diagonal ones as sorted unique keys
    I * nc + J; the sorting order of their entries (I, J) then (J, I); and the pattern
    of both triangles (offsets, cols)."""
    offd = big_i != big_j
    pairs = np.unique(big_i[offd] * nc + big_j[offd])
    rows = np.concatenate([pairs // nc, pairs % nc])
    cols = np.concatenate([pairs % nc, pairs // nc])
    order = np.lexsort((cols, rows))
    return pairs, order, _csr_offsets(nc, rows), cols[order]


def _ranges(start, length):
    """For ranges [start[k], start[k] + length[k]): each member's range k and index."""
    which = np.repeat(np.arange(len(start)), length)
    within = np.arange(len(which)) - np.repeat(np.cumsum(length) - length, length)
    return which, start[which] + within


def _cartesian(a_start, a_len, b_start, b_len):
    """For each k, all pairs (a, b) of [a_start[k], +a_len[k]) x [b_start[k], +b_len[k]),
    a-major: each pair's k, a and b."""
    which, flat = _ranges(np.zeros_like(a_start), a_len * b_len)
    width = np.maximum(b_len[which], 1)
    return which, a_start[which] + flat // width, b_start[which] + flat % width


def _keys(rows, cols, width):
    """One sortable int64 key per entry of the CSR pattern ``rows``/``cols`` (sorted
    columns per row; columns below ``width``): row * width + col, ascending."""
    return np.repeat(np.arange(len(rows) - 1, dtype=np.int64), np.diff(rows)) * width + cols


def _find(rows, cols, i, j):
    """Index in a CSR pattern (sorted columns per row) of the entries (i[k], j[k]), all present."""
    width = int(cols.max()) + 1
    return np.searchsorted(_keys(rows, cols, width), i * width + j)


# ----------------------------------------------------------------- numeric (numpy)
# The same products as the per-step kernels, on numpy arrays: for the setup (the
# coarse levels' strength at rest) and as the tests' reference.


def smooth_prolongation(level, diag, off, dinv, scale, tent):
    """P = T - scale D^-1 A T in P's pattern (scale = omega / rho), T's blocks ``tent``
    (nf, bf, 6) from ``tentative``; blocks (np, bf, 6)."""
    t = level.transfer
    at = np.zeros((len(t.p_cols), t.bf, COARSE_BS))
    has = t.tent_slot >= 0
    np.add.at(at, t.tent_slot[has], np.einsum("nij,njk->nik", diag[has], tent[has]))
    ok = level.entry_slot >= 0
    np.add.at(at, level.entry_slot[ok], np.einsum("eij,ejk->eik", off[ok], tent[level.off_cols[ok]]))
    p_owner = np.repeat(np.arange(level.n), np.diff(t.p_rows))
    p = -scale * np.einsum("nij,njk->nik", dinv[p_owner], at)
    p[t.tent_slot[has]] += tent[has]
    return p


def filtered_operator(level, diag, off, rows):
    """Level 0's operators after ``filter_fine``, from the full one (``rest_operator``'s
    ``diag`` (n, 3, 3), ``off`` (2m, 3, 3) over the adjacency entries with offsets
    ``rows``): the diagonal blocks of the strong couplings alone (P's smoothing), those
    of the kept couplings and the kept entries' blocks (P^T A' P). A coupling left out
    takes its spring off the diagonal too: A_ii + A_ij."""
    owner = np.repeat(np.arange(level.n), np.diff(rows))
    kept = np.zeros(len(off), dtype=bool)
    kept[level.entry] = True
    smooth = np.zeros(len(off), dtype=bool)
    smooth[level.entry[level.smooth] if level.smooth is not None else level.entry] = True
    diag_kept = diag.copy()
    np.add.at(diag_kept, owner[~kept], off[~kept])
    diag_smooth = diag_kept.copy()
    np.add.at(diag_smooth, owner[kept & ~smooth], off[kept & ~smooth])
    return diag_smooth, diag_kept, off[level.entry]


def galerkin(level, diag, off, p):
    """The coarse operator P^T A P: (diagonal blocks (nc, 6, 6), off-diagonal blocks)."""
    t = level.transfer
    ap = np.zeros((len(level.ap_cols), t.bf, COARSE_BS))
    a = np.where((level.apt_entry < 0)[:, None, None], diag[np.repeat(np.arange(level.n),
                                                                        np.diff(level.apt_rows))],
                 off[np.maximum(level.apt_entry, 0)])
    np.add.at(ap, level.apt_ap, np.einsum("eij,ejk->eik", a, p[level.apt_p]))
    products = np.einsum("eji,ejk->eik", p[level.gal_p], ap[level.gal_ap])
    sums = np.add.reduceat(products, level.gal_rows[:-1], axis=0) if len(products) else products
    c_diag = np.zeros((t.nc, COARSE_BS, COARSE_BS))
    c_off = np.zeros((len(level.c_mirror), COARSE_BS, COARSE_BS))
    is_diag = level.gal_block < 0
    c_diag[-1 - level.gal_block[is_diag]] = sums[is_diag]
    c_off[level.gal_block[~is_diag]] = sums[~is_diag]
    lower = np.setdiff1d(np.arange(len(c_off)), level.gal_block[~is_diag])
    c_off[lower] = np.transpose(c_off[level.c_mirror[lower]], (0, 2, 1))
    return c_diag, c_off


@dataclass
class Hierarchy:
    """The levels of a model's hierarchy, finest first; the last has no transfer."""

    levels: list

    @property
    def sizes(self):
        return [level.n * level.bs for level in self.levels]


def rest_operator(model, dt, free):
    """Level 0's operator at rest (springs unstretched: blocks b n n^T, b = dt kd +
    dt^2 ks, directions at the initial state) over the adjacency entries: (diag
    (n, 3, 3), off (2m, 3, 3), off_rows, off_cols); couplings to pinned particles are
    zero (they are not solved for). The tests' reference of the level-0 operator's
    structure; ``build`` needs only its norms (``rest_couplings``)."""
    from massspring.device import adjacency

    offsets, other, entry = adjacency(model)
    spring = np.where(entry >= 0, entry, -1 - entry)
    block = _rest_blocks(model, dt)
    owner = np.repeat(np.arange(model.n_particles), np.diff(offsets))
    live = free[owner] & free[other]
    off = np.where(live[:, None, None], -block[spring], 0.0)
    diag = model.masses[:, None, None] * np.eye(3)
    np.add.at(diag, owner[live], block[spring[live]])
    return diag, off, offsets.astype(np.int64), other.astype(np.int64)


def _rest_blocks(model, dt):
    x, ends = model.positions, model.springs
    d = x[ends[:, 1]] - x[ends[:, 0]]
    length = np.linalg.norm(d, axis=1)
    nvec = np.divide(d, length[:, None], out=np.zeros_like(d), where=length[:, None] > 0)
    b = dt * model.damping + dt * dt * model.stiffness
    return b[:, None, None] * nvec[:, :, None] * nvec[:, None, :]


def rest_couplings(model, dt, free):
    """Strength data of level 0 at rest: coupling pairs (k, 2) of free particles, their
    Frobenius norms b (parallel springs add up later), and each particle's ||A_ii||."""
    ends = model.springs
    block = _rest_blocks(model, dt)
    live = free[ends[:, 0]] & free[ends[:, 1]]
    diag = model.masses[:, None, None] * np.eye(3)
    for end in (0, 1):
        np.add.at(diag, ends[live, end], block[live])
    weights = np.linalg.norm(block, axis=(1, 2))
    return ends[live], weights[live], np.linalg.norm(diag, axis=(1, 2))


def coarse_couplings(pairs, weights, diag_norm, agg, count):
    """The next level's strength data: couplings between aggregates summed, each
    aggregate's diagonal norm the sum of its members' and of its inner couplings'."""
    a, b = agg[pairs[:, 0]], agg[pairs[:, 1]]
    ok = (a >= 0) & (b >= 0)
    inner = ok & (a == b)
    diag = np.zeros(count)
    members = agg >= 0
    np.add.at(diag, agg[members], diag_norm[members])
    np.add.at(diag, a[inner], 2 * weights[inner])
    between = ok & (a != b)
    return np.stack([a[between], b[between]], 1), weights[between], diag


def strong_entries(offsets, other, free, s_rows, s_cols):
    """Which adjacency entries (of ``other``) are level 0's strong couplings (bool): those
    in the strength graph ``s_rows``/``s_cols``, and every entry to a pinned particle (it
    adds nothing off the diagonal, P's rows there being zero, but holds A_ii)."""
    n = len(offsets) - 1
    owner = np.repeat(np.arange(n), np.diff(offsets))
    return _in_pattern(s_rows, s_cols, owner, other) | ~(free[owner] & free[other])


def _in_pattern(rows, cols, i, j):
    """Whether each (i[k], j[k]) is an entry of the CSR pattern ``rows``/``cols`` (sorted
    columns per row)."""
    n = max(len(rows) - 1, int(j.max(initial=0)) + 1)
    keys = _keys(rows, cols, n)
    wanted = i.astype(np.int64) * n + j
    at = np.minimum(np.searchsorted(keys, wanted), max(len(keys) - 1, 0))
    return (keys[at] == wanted) if len(keys) else np.zeros(len(wanted), dtype=bool)


def within_pattern(t, i, k, c_rows, c_cols):
    """For each entry (i[e], k[e]): whether every coarse pair (I, J), I an aggregate of
    P's row i and J one of row k (transfer ``t``), is a diagonal (I = J) or in the
    coarse pattern ``c_rows``/``c_cols``: the coupling A_ik adds no block to P^T A P."""
    p_len = np.diff(t.p_rows)
    pair, p_i, p_k = _cartesian(t.p_rows[i], p_len[i], t.p_rows[k], p_len[k])
    big_i, big_j = t.p_cols[p_i], t.p_cols[p_k]
    ok = (big_i == big_j) | _in_pattern(c_rows, c_cols, big_i, big_j)
    return np.bincount(pair[~ok], minlength=len(i)) == 0


def filter_fine(level, free, agg, count, s_rows, s_cols):
    """Level 0's transfer and index lists with its weak couplings filtered (see the
    module docstring): P smoothed by the strong couplings alone; P^T A' P with A' the
    strong couplings and the weak ones that add no coarse block. Sets ``level.entry``
    (the kept adjacency entries), ``level.smooth`` and the pattern of the kept ones;
    returns the next level's pattern (that of the strong couplings alone)."""
    rows, cols = level.off_rows, level.off_cols
    owner = np.repeat(np.arange(level.n), np.diff(rows))
    strong = strong_entries(rows, cols, free, s_rows, s_cols)
    strong_rows = _csr_offsets(level.n, owner[strong])
    level.transfer = transfer(level.n, level.bs, agg, count, strong_rows, cols[strong])
    c_rows, c_cols = coarse_pattern(Level(level.n, level.bs, strong_rows, cols[strong], transfer=level.transfer))
    keep = strong.copy()
    weak = np.flatnonzero(~strong)
    keep[weak] = within_pattern(level.transfer, owner[weak], cols[weak], c_rows, c_cols)
    level.entry = np.flatnonzero(keep)
    level.smooth = strong[level.entry]
    level.off_rows, level.off_cols = _csr_offsets(level.n, owner[keep]), cols[keep]
    return link(level)


def build(model, dt, theta=THETA, max_coarse=MAX_COARSE, filter_weak=None):
    """The hierarchy of ``model`` for time step ``dt`` (s): structure only (see the
    module docstring). Coarse levels are aggregated on the coupling graph that the
    aggregates inherit (summed norms), not on numeric coarse operators. ``filter_weak``
    (default ``FILTER_WEAK``): level 0's weak couplings filtered (``filter_fine``)."""
    from massspring.device import adjacency

    free = model.free_mask()
    offsets, other, _ = adjacency(model)
    pairs, weights, diag_norm = rest_couplings(model, dt, free)
    level = Level(model.n_particles, 3, offsets.astype(np.int64), other.astype(np.int64))
    level.entry = np.arange(len(other))
    levels = [level]
    while level.n * level.bs > max_coarse and len(levels) < MAX_LEVELS:
        s_rows, s_cols, s_w = strength_graph(level.n, pairs, weights, diag_norm,
                                             theta if len(levels) == 1 else COARSE_THETA)
        agg, count = aggregate(s_rows, s_cols, s_w)
        if len(levels) == 1:
            agg[~free] = -1
        if count == 0 or count * COARSE_BS >= 0.8 * level.n * level.bs:
            break  # no useful coarsening
        if len(levels) == 1 and (FILTER_WEAK if filter_weak is None else filter_weak):
            next_rows, next_cols = filter_fine(level, free, agg, count, s_rows, s_cols)
        else:
            level.transfer = transfer(level.n, level.bs, agg, count, level.off_rows, level.off_cols)
            next_rows, next_cols = link(level)
        pairs, weights, diag_norm = coarse_couplings(pairs, weights, diag_norm, agg, count)
        level = Level(count, COARSE_BS, next_rows, next_cols)
        levels.append(level)
    return Hierarchy(levels)
