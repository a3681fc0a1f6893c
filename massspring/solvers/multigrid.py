"""Smoothed-aggregation multigrid: a V-cycle as the preconditioner of the CG.

The hierarchy's structure comes from the spring graph, once per simulation
(``aggregation.build``): aggregates and the patterns of P, A P and P^T A P. Every
step, after the operator's refresh, ``setup`` recomputes the values in kernels
(``kernels/multigrid.py``): the tentative prolongations T (translations and
rotations of each aggregate at the current positions, orthonormalized), D^-1 on
each level, the smoothed prolongations P = (I - omega/rho D^-1 A) T, the Galerkin
coarse operators P^T A P and the dense Cholesky factor of the coarsest level (on
level 0 without the weak couplings that would widen the coarse levels,
``aggregation.filter_fine``). The fine level stays matrix-free.

The whole setup runs every step (issue 22; ``benchmarks/multigrid_reuse.py`` measured
the alternatives, its results in ``benchmarks/results/multigrid_reuse_*.json``). A
hierarchy kept for later steps with only level 0's D^-1 and rho refreshed
(``fine_level``) still gives a symmetric positive definite cycle, so CG still meets
its tolerance: the fine smoother is convergent for the current A and the stale coarse
cycle enters only as G S P B_c P^T S G^T (G the smoother's error propagation, S the
constraint filter), positive semidefinite for any symmetric positive semidefinite
coarse cycle B_c. But the coarse levels carry the soft modes of a stiff, anisotropic
A whose spring directions turn with the cloth, and a hierarchy one step old multiplies
CG's iterations on a moving cloth many times over, costing far more than the setup it
saves; recomputing the Galerkin operators from a stale P (``coarse_operators`` only)
adds fewer iterations but saves little, since T and P (``prolongation``) are the cheap
part. Only an undeformed cloth in free fall, whose A does not change, gains.

``apply`` is one V(NU, NU)-cycle on CG's residual: Chebyshev smoothing of degree
NU in D^-1 A on [rho / CHEB_RATIO, rho] before and after the coarse correction
(the same polynomial, so the cycle is symmetric; it is positive definite when A
is), with rho an upper bound of the spectral radius of D^-1 A: 2 on level 0 with
the definiteness fix (then A = M + sum of positive semidefinite spring blocks),
else the largest block row sum of |D^-1 A|; on coarse levels 1.1 times a
Lanczos estimate of 10 steps or more, until it stops growing (``_lanczos``; a
row-sum bound is useless there: 6x6 blocks mix translation and rotation scales).
Each coarse level is visited once per cycle
(``W_CYCLE = True`` gives every level but the last two a second visit instead;
``benchmarks/multigrid_cycles.py`` compares the two shapes: the W-cycle saves under
one CG iteration per step and costs more than that saves). Constrained (pinned)
directions are filtered out of its input and output.
"""

from __future__ import annotations

import math

import numpy as np
import taichi as ti

from massspring.device import POOL, Layout, capacity
from massspring.kernels import multigrid as mg
from massspring.solvers import aggregation
from massspring.solvers.base import Preconditioner

NU = 3              # Chebyshev degree of each smoothing (pre and post)
CHEB_RATIO = 30.0   # the smoother targets eigenvalues of D^-1 A in [rho / CHEB_RATIO, rho]
OMEGA = 4.0 / 3.0   # prolongation smoothing weight (times 1 / rho)
LANCZOS_STEPS = 10  # per coarse level and step, for rho(D^-1 A), at least ...
LANCZOS_MAX = 30    # ... and at most, while the estimate still grows by LANCZOS_RTOL over 2 steps
LANCZOS_RTOL = 0.01
RHO_SAFETY = 1.1    # Lanczos underestimates rho; Chebyshev diverges if rho is too low by ~10%
W_CYCLE = False     # True: two coarse cycles on every level but the last two
FLOOR = 256         # smallest capacity of the hierarchy's arrays


class Multigrid(Preconditioner):
    """Smoothed-aggregation V-cycle (see the module docstring); a global preconditioner."""

    name = "multigrid"
    kernel = None
    # parallel loops pay from fewer springs than for the other solvers: the crossover of
    # benchmarks/switch_point.py's multigrid column (results/switch_point_multigrid.json)
    serial_below = 64_000

    @classmethod
    def declare(cls, layout, model, settings, cfg):
        real = layout.real
        layout.add("minv", real, "particle", (3, 3))
        for name in ("mg_x", "mg_res", "mg_d", "mg_d2"):
            layout.vectors(name, real)

    def __init__(self, dev, model, settings):
        super().__init__(dev, model, settings)
        self.serial = settings.loops == "serial"
        self.fix = settings.definiteness_fix
        self.hierarchy = aggregation.build(model, settings.dt)
        self.cfg = None  # the integrator's Config, set by ``bind``
        self.plan = _Plan(self.hierarchy)
        layout = self.hierarchy_layout(dev.x.dtype) if len(self.hierarchy.levels) > 1 else None
        self.nbytes = layout.nbytes() if layout is not None else 0
        self.g = layout.allocate() if layout is not None else None
        self.rho = [1.0] * len(self.hierarchy.levels)
        self.cheb = [None] * len(self.hierarchy.levels)  # (coefficients, degree): ``_set_rho``
        self.factor_failed = 0
        self.lanczos_steps = []  # Lanczos steps of each coarse level in the last setup

    def hierarchy_layout(self, real) -> Layout:
        """The declarations of the hierarchy's fields (``_Plan.layout``)."""
        return self.plan.layout(real)

    def bind(self, cfg):
        self.cfg = cfg

    # ------------------------------------------------------------------ setup
    def setup(self, dt):
        self.fine_level()
        if self.g is None:
            return
        self.prolongation()
        self.coarse_operators()

    def fine_level(self):
        """Level 0's D^-1 (``dev.minv``) and rho[0], the bound its smoother needs."""
        bound = mg.fine_inverse(self.dev, self.cfg, self.serial)
        self._set_rho(0, min(2.0, bound) if self.fix else bound)

    def _set_rho(self, level, rho):
        """rho of ``level`` and the Chebyshev coefficients of its smoothing (``chebyshev``)."""
        self.rho[level] = rho
        inv_theta, steps = chebyshev(rho)
        coef = [inv_theta] + [c for step in steps for c in step]
        self.cheb[level] = (coef + [0.0] * (len(mg.COEF_ZERO) - len(coef)), len(steps))

    def prolongation(self):
        """The tentative prolongations T of every level at the current positions and
        level 0's smoothed P (after ``fine_inverse``)."""
        dev, cfg, g, plan, serial = self.dev, self.cfg, self.g, self.plan, self.serial
        mg.tentative0(dev, cfg, g, plan.node_range[1][1], aggregation.DROP, serial)
        for level in range(1, plan.levels - 1):
            mg.tentativec(cfg, g, *plan.node_range[level + 1], aggregation.DROP, serial)
        mg.smooth_p0(dev, cfg, g, OMEGA / _positive(self.rho[0]), serial)

    def coarse_operators(self):
        """From level 0's P and the current A: the coarse operators, their D^-1 and rho,
        the coarse levels' P and the coarsest Cholesky factor."""
        dev, cfg, g, plan, serial = self.dev, self.cfg, self.g, self.plan, self.serial
        self.lanczos_steps = []
        mg.ap0(dev, cfg, g, serial)
        mg.galerkin0(cfg, g, plan.gal0_count, serial)
        last = plan.levels - 1
        for level in range(1, plan.levels):
            begin, end = plan.lower_range[level]
            if end > begin:
                mg.mirror(cfg, g, begin, end, serial)
            nodes = plan.node_range[level]
            if level == last:
                self.factor_failed = int(mg.factor_coarsest(cfg, g, nodes[0], nodes[1] - nodes[0]))
                break
            mg.coarse_inverse(cfg, g, nodes[0], nodes[1], serial)
            self._set_rho(level, RHO_SAFETY * self._lanczos(nodes[0], nodes[1]))
            mg.smooth_pc(cfg, g, nodes[0], nodes[1], OMEGA / _positive(self.rho[level]), serial)
            mg.apc(cfg, g, nodes[0], nodes[1], serial)
            mg.galerkinc(cfg, g, *plan.gal_range[level], serial)

    def _lanczos(self, begin, end):
        """The largest Ritz value of D^-1 A on coarse nodes [begin, end): after
        LANCZOS_STEPS steps, and on while it grew by more than LANCZOS_RTOL over the
        last two (at most LANCZOS_MAX). A top eigenvalue the start vector barely holds
        shows late: on a swinging 128 x 128 cloth, the 8th step's value was 0.81 of
        the 20th's and the 10th's 0.97. An estimate that low makes the Chebyshev
        smoother amplify the top modes: with 7 or 8 steps and no more, CG took 41-692
        iterations on one step of such cloths instead of 7-15 (with every coupling in
        the coarse levels; since level 0's weak ones are filtered the cliff sits lower,
        at 3-4 steps: ``test_lanczos_goes_on_while_its_estimate_grows``)."""
        cfg, g, serial = self.cfg, self.g, self.serial
        beta = math.sqrt(max(mg.lanczos_start(cfg, g, begin, end, serial), 0.0))
        alphas, betas, ritz = [], [], {}
        while len(alphas) < LANCZOS_MAX and math.isfinite(beta) and beta > 0:
            alpha = float(mg.lanczos_apply(cfg, g, begin, end, 1.0 / beta, serial))
            previous = beta if alphas else 0.0
            beta = math.sqrt(max(float(mg.lanczos_next(cfg, g, begin, end, alpha, previous, serial)), 0.0))
            alphas.append(alpha)
            betas.append(beta)
            k = len(alphas)
            if k >= LANCZOS_STEPS - 2:
                ritz[k] = _top_ritz(alphas, betas)
                if k >= LANCZOS_STEPS and k - 2 in ritz and ritz[k] <= (1.0 + LANCZOS_RTOL) * ritz[k - 2]:
                    break
        self.lanczos_steps.append(len(alphas))
        if not alphas:
            return 1.0
        return ritz[len(alphas)] if len(alphas) in ritz else _top_ritz(alphas, betas)

    # ------------------------------------------------------------------ cycle
    def apply(self):
        """z = B r (one V-cycle) into ``dev.z`` from ``dev.r``; returns r . z."""
        dev, cfg, g = self.level0()
        serial = self.serial
        coarse = g is not None
        coef, degree = self.cheb[0]
        mg.down0(dev, cfg, g, coef, degree, coarse, self.plan.node_range[1][1] if coarse else 0, serial)
        if coarse:
            self._visits(1)
        return float(mg.up0(dev, cfg, g, coef, degree, coarse, serial))

    def level0(self):
        """(fields, Config, hierarchy fields) that level 0's part of the cycle runs on: the
        run's (``multigrid_f32``: f32 copies)."""
        return self.dev, self.cfg, self.g

    def _visits(self, level):
        """The coarse correction from ``level``: one cycle (two under ``W_CYCLE`` unless it is the last)."""
        self._coarse(level, True)
        if W_CYCLE and level < self.plan.levels - 1:
            self._coarse(level, False)

    def _coarse(self, level, first):
        """A cycle on ``level`` for its right-hand side ``c_b``: from x = 0 (``first``), else
        from the current ``c_x`` (the W-cycle's second visit: x + B (b - A x))."""
        cfg, g, serial, plan = self.cfg, self.g, self.serial, self.plan
        begin, end = plan.node_range[level]
        if level == plan.levels - 1:
            mg.solve_coarsest(cfg, g, begin, end - begin)
            return
        coef, degree = self.cheb[level]
        mg.downc(cfg, g, begin, end, first, coef, degree, *plan.node_range[level + 1], serial)
        self._visits(level + 1)
        mg.upc(cfg, g, begin, end, coef, degree, serial)

    def release(self):
        if self.g is not None:
            POOL.give(self.g)
            self.g = None

    def describe(self):
        """Bytes of the hierarchy's fields and the unknowns of each level."""
        return {"bytes": self.nbytes, "levels": self.hierarchy.sizes}


def chebyshev(rho, degree=NU, ratio=CHEB_RATIO):
    """Coefficients of a degree-``degree`` Chebyshev smoother for D^-1 A on
    [rho / ratio, rho] (Saad, Iterative Methods, Alg. 12.1): (1 / theta, [(c1, c2), ...])
    with d_0 = D^-1 r / theta and d_{k+1} = c1 d_k + c2 D^-1 r_{k+1} (the last step
    has no next direction)."""
    rho = _positive(rho)
    low = rho / ratio
    theta, delta = 0.5 * (rho + low), 0.5 * (rho - low)
    sigma = theta / delta
    rh = 1.0 / sigma
    steps = []
    for _ in range(degree - 1):
        rh_new = 1.0 / (2.0 * sigma - rh)
        steps.append((rh_new * rh, 2.0 * rh_new / delta))
        rh = rh_new
    steps.append((0.0, 0.0))
    return 1.0 / theta, steps


def _top_ritz(alphas, betas):
    """The largest eigenvalue of the Lanczos tridiagonal of ``alphas`` and ``betas``."""
    k = len(alphas)
    return float(np.linalg.eigvalsh(np.diag(alphas) + np.diag(betas[:k - 1], 1) + np.diag(betas[:k - 1], -1))[-1])


def _positive(value):
    return value if math.isfinite(value) and value > 0 else 1.0


class _Plan:
    """The hierarchy's index lists made global, for one bundle of fields.

    The coarse levels are stored together: level l's nodes are ``node_range[l]`` of
    the global node numbering and its off-diagonal blocks follow those of the levels
    above it. Every per-level index list of ``aggregation.Level`` is shifted by the
    offsets of the arrays it indexes (nodes, off-diagonal blocks, P blocks, A P blocks,
    ...) and concatenated over the levels; ``arrays`` holds the results by field name.
    ``counts`` sizes the value fields; ``gal0_count``, ``gal_range``, ``lower_range``
    and ``coarsest`` are what ``setup`` passes the kernels per level.
    """

    def __init__(self, hierarchy):
        levels = hierarchy.levels
        self.levels = len(levels)
        self.arrays = {}
        if self.levels < 2:
            return
        coarse = levels[1:]
        self.node_base = _offsets([lv.n for lv in coarse])             # first global node of each coarse level
        self.off_base = _offsets([len(lv.off_cols) for lv in coarse])  # first off-diagonal block of each
        self.node_range = {l: (int(self.node_base[l - 1]), int(self.node_base[l])) for l in range(1, self.levels)}
        self.counts = {"fine": levels[0].n, "nodes": int(self.node_base[-1]), "off": int(self.off_base[-1])}
        self._fine_transfer(levels[0])
        self._coarse_operators(levels)
        self._coarse_transfers(levels)
        self.coarsest = levels[-1].n * levels[-1].bs

    def _fine_transfer(self, fine):
        """Level 0 -> 1: P's pattern, A P, the Galerkin products and P^T (level 0's own
        numbering: nothing to shift)."""
        t, a = fine.transfer, self.arrays
        a["t0_slot"], a["e0_slot"] = t.tent_slot, fine.entry_slot
        a["s0_rows"], a["s0_entry"] = fine.off_rows, fine.entry
        smooth = np.ones(len(fine.entry), dtype=bool) if fine.smooth is None else fine.smooth
        a["s0_smooth"] = smooth.astype(np.int64)
        a["agg0_rows"], a["agg0_members"] = t.member_rows, t.members
        a["p0_rows"], a["p0_cols"] = t.p_rows, t.p_cols
        a["ap0_rows"] = fine.ap_rows
        a["apt0_rows"], a["apt0_ap"] = fine.apt_rows, fine.apt_ap
        a["gal0_rows"], a["gal0_block"], a["gal0_p"], a["gal0_ap"] = (fine.gal_rows, fine.gal_block, fine.gal_p,
                                                                      fine.gal_ap)
        a["pt0_rows"], a["pt0_block"], a["pt0_fine"] = fine.pt_rows, fine.pt_block, fine.pt_fine
        self.gal0_count = len(fine.gal_block)
        self.counts.update(p0=len(t.p_cols), ap0=len(fine.ap_cols))

    def _coarse_operators(self, levels):
        """Each coarse level's operator pattern (CSR over global nodes), the transpose of
        each off-diagonal block, and the lower-triangle blocks ``mirror`` fills in (those
        the Galerkin products of the level above do not target): ``lower_range[l]``."""
        rows, cols, mirrors, lower = [np.zeros(1, dtype=np.int64)], [], [], []
        self.lower_range = {}
        done = 0
        for l in range(1, self.levels):
            level, above = levels[l], levels[l - 1]
            off, nodes = self.off_base[l - 1], self.node_base[l - 1]
            rows.append(level.off_rows[1:] + off)
            cols.append(level.off_cols + nodes)
            mirrors.append(above.c_mirror + off)
            targeted = above.gal_block[above.gal_block >= 0]
            untargeted = np.setdiff1d(np.arange(len(level.off_cols)), targeted) + off
            self.lower_range[l] = (done, done + len(untargeted))
            done += len(untargeted)
            lower.append(untargeted)
        a = self.arrays
        a["c_rows"], a["c_cols"] = np.concatenate(rows), _cat(cols)
        a["c_mirror"], a["lower"] = _cat(mirrors), _cat(lower)

    def _coarse_transfers(self, levels):
        """Level l -> l + 1 for l >= 1: the same lists as level 0's, shifted to global
        numbering. CSR row offsets are written at their level's global rows; the P, A P,
        triple-product, Galerkin-pair, P^T and member lists are concatenated, each
        level's entries shifted by the sizes of the levels before it (``base``)."""
        nodes, off = self.counts["nodes"], self.counts["off"]
        tc_slot = np.full(nodes, -1, dtype=np.int64)
        ec_slot = np.full(off, -1, dtype=np.int64)
        csr = {key: np.zeros(nodes + 1, dtype=np.int64) for key in ("pc_rows", "apc_rows", "aptc_rows", "ptc_rows",
                                                                    "aggc_rows")}
        parts = {key: [] for key in ("pc_cols", "aptc_ap", "galc_block", "galc_p", "galc_ap", "ptc_block",
                                     "ptc_fine", "aggc_members")}
        galc_rows = [np.zeros(1, dtype=np.int64)]
        base = dict.fromkeys(("p", "ap", "apt", "gal_pairs", "gal_blocks", "pt", "members"), 0)
        self.gal_range = {}
        for l in range(1, self.levels - 1):
            level, t = levels[l], levels[l].transfer
            n0, n1 = self.node_range[l]         # this level's nodes
            c0, c1 = self.node_range[l + 1]     # the next level's
            tc_slot[n0:n1] = np.where(t.tent_slot >= 0, t.tent_slot + base["p"], -1)
            ec_slot[self.off_base[l - 1]:self.off_base[l]] = np.where(level.entry_slot >= 0,
                                                                      level.entry_slot + base["p"], -1)
            csr["pc_rows"][n0 + 1:n1 + 1] = t.p_rows[1:] + base["p"]
            csr["apc_rows"][n0 + 1:n1 + 1] = level.ap_rows[1:] + base["ap"]
            csr["aptc_rows"][n0 + 1:n1 + 1] = level.apt_rows[1:] + base["apt"]
            csr["ptc_rows"][c0 + 1:c1 + 1] = level.pt_rows[1:] + base["pt"]
            csr["aggc_rows"][c0 + 1:c1 + 1] = t.member_rows[1:] + base["members"]
            parts["aggc_members"].append(t.members + n0)
            parts["pc_cols"].append(t.p_cols + c0)
            parts["aptc_ap"].append(level.apt_ap + base["ap"])
            # a diagonal block (-1 - node) gets the global node, an off-diagonal one the global block
            parts["galc_block"].append(np.where(level.gal_block < 0, level.gal_block - c0,
                                                level.gal_block + self.off_base[l]))
            parts["galc_p"].append(level.gal_p + base["p"])
            parts["galc_ap"].append(level.gal_ap + base["ap"])
            galc_rows.append(level.gal_rows[1:] + base["gal_pairs"])
            parts["ptc_block"].append(level.pt_block + base["p"])
            parts["ptc_fine"].append(level.pt_fine + n0)
            self.gal_range[l] = (base["gal_blocks"], base["gal_blocks"] + len(level.gal_block))
            base["p"] += len(t.p_cols)
            base["ap"] += len(level.ap_cols)
            base["apt"] += len(level.apt_p)
            base["gal_pairs"] += len(level.gal_p)
            base["gal_blocks"] += len(level.gal_block)
            base["pt"] += len(level.pt_block)
            base["members"] += len(t.members)
        a = self.arrays
        for key, offsets in csr.items():
            np.maximum.accumulate(offsets, out=offsets)  # rows of levels without entries continue the last offset
            a[key] = offsets
        a["tc_slot"], a["ec_slot"] = tc_slot, ec_slot
        for key, values in parts.items():
            a[key] = _cat(values)
        a["galc_rows"] = np.concatenate(galc_rows)
        self.counts.update(pc=base["p"], apc=base["ap"], gal_blocks=base["gal_blocks"])

    def layout(self, real) -> Layout:
        """Declarations of the hierarchy's fields, sized by capacity classes."""
        layout = Layout(0, 0, real)
        c = self.counts

        def cap(count):
            return capacity(count, FLOOR)

        for name, values in self.arrays.items():
            layout.add(name, ti.i32, cap(len(values)), values=values.astype(np.int32))
        layout.add("t0", real, cap(c["fine"]), (3, 6))
        layout.add("tc", real, cap(c["nodes"]), (6, 6))
        layout.add("c_cand", real, cap(c["nodes"]), (6, 6))      # each coarse node's candidates (R)
        layout.vectors("c_centre", real, cap(c["nodes"]))        # and the centre of its rotations
        layout.add("p0", real, cap(c["p0"]), (3, 6))
        layout.add("ap0", real, cap(c["ap0"]), (3, 6))
        layout.add("pc", real, cap(c["pc"]), (6, 6))
        layout.add("apc", real, cap(c["apc"]), (6, 6))
        layout.add("apc_tmp", real, cap(c["pc"]), (6, 6))        # A T while P is smoothed
        layout.add("gal_tmp", real, cap(c["gal_blocks"]), (6, 6))  # Galerkin sums
        for name in ("c_diag", "c_dinv"):
            layout.add(name, real, cap(c["nodes"]), (6, 6))
        layout.add("c_off", real, cap(c["off"]), (6, 6))
        for name in ("c_b", "c_x", "c_res", "c_d", "c_d2"):
            layout.vectors(name, real, cap(c["nodes"]), k=6)
        layout.vectors("c_partial", ti.f64, cap(c["nodes"] // 256 + 1), k=2)
        layout.add("chol", real, capacity(self.coarsest ** 2, FLOOR))
        layout.add("chol_y", real, capacity(self.coarsest, FLOOR))
        return layout


def _cat(parts):
    parts = [np.asarray(p, dtype=np.int64) for p in parts if len(p)]
    return np.concatenate(parts) if parts else np.zeros(1, dtype=np.int64)


def _offsets(sizes):
    """[0, s0, s0 + s1, ...]: where each of consecutive blocks of ``sizes`` starts (int64)."""
    return np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
