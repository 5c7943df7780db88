"""Wandering gyro biases (``bias_random_walk``, ``bias_instability``) as
candidates of ``calib diagnose --method gyro`` (issue 18).

The gyro method's equations (static means, transitions between positions,
turns of known angle; methods/gyro.py) each see the gyro bias over their own
stretch of the record: a wandering bias b(t) moves them by r = J b, with J
the (whitened) response of the equations to a bias held over each
PIECE_S-second piece of the record (finite differences on the data). A bias
process of figure x per axis (random walk: density q, covariance q^2 min(t, t');
flicker: the catalogue's Gauss-Markov sum, covariance FLICKER_SCALE^2 B^2
sum_k exp(-|t - t'| / T_k); both taken as the covariance of the process's means over
the pieces, ``piece_cov``) makes the equations' covariance

    V = I + sum_axis x_axis^2 M_axis,   M_axis = J_axis C_unit J_axis^T,

The equations are the gyro fit's own and, below them, the within-static
contrasts of the gyro's PIECE_S-second means (``SubMeans``): under white
noise these carry nothing of the constant-rate model, but they carry the
wander's short-tau spectrum, which the fit's ~80 equations average away; with
them the figure's relative Cramer-Rao bound on the validation plan drops from
0.18-0.19 to 0.13-0.14 and flicker is told from a random walk. Linearised
about the white fit of the deterministic model (Jacobian A of its
parameters), the generalised least-squares -2 log L

    -2 log L(x) = min_d (r + A d)^T V^-1 (r + A d) + log det V

is profiled over the figures x (per axis). The candidate's score is the
drop of the profiled -2 log L from the current model (the likelihood ratio,
as every other candidate's; with no wander V = I and -2 log L is the white
chi^2). The figures reported and used afterwards maximise the restricted
likelihood (-2 log L + log det A^T V^-1 A): the plain maximum shrinks them
by the parameters fitted beside them (0.6-0.9x the truth on a hidden walk)
and leaves the whitened residual ~8 % above the floor. The process is a noise-model term: the
deterministic parameters stay those of the white fit (``fit gyro`` gives
them), their covariance becomes the sandwich (A^T A)^-1 A^T V A (A^T A)^-1
(the wander widens sigma) and the figures go to ``stats.noise_model``; the
final residual is the whitened one (both on the fit's own equations, whose
estimator the parameters are).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy.linalg import cholesky, solve_triangular

from calib_cli.model.effects import FLICKER_SCALE, FLICKER_TAUS

PIECE_S = 1.0  # s, the pieces over which the bias is held in J
KEYS = {"bias_random_walk": "gyro_bias_rw", "bias_instability": "gyro_bias_instability"}
NOTE = "a noise-model term: it widens sigma; never applied or exported"


def piece_cov(kind: str, npc: int, P: float = PIECE_S, exact: bool = True) -> np.ndarray:
    """Covariance of the bias process's means over the npc pieces of P seconds, per
    unit figure. exact=False: the process's covariance at the pieces' centres."""
    tc = (np.arange(npc) + 0.5) * P
    if kind == "bias_random_walk":  # q^2 min(t, t'); a piece's own mean: c - P/6
        C = np.minimum.outer(tc, tc)
        if exact:
            C[np.diag_indices(npc)] -= P / 6.0
        return C
    D = np.abs(np.subtract.outer(tc, tc))
    C = np.zeros((npc, npc))
    for T in FLICKER_TAUS:  # sum of exp(-|t - t'| / T), FLICKER_SCALE^2 B^2 each
        if not exact:
            C += np.exp(-D / T)
            continue
        a = T / P
        off = a * a * (np.exp(-(D - P) / T) + np.exp(-(D + P) / T) - 2.0 * np.exp(-D / T))
        own = 2.0 * a * (1.0 - a * (-np.expm1(-P / T)))
        C += np.where(D > 0, off, own)
    return FLICKER_SCALE ** 2 * C


class SubMeans:
    """The within-static contrasts of the gyro's PIECE_S-second means: per static position
    and axis, the whitened means of the pieces wholly inside it (without its first and
    last samples, which the transitions integrate), projected orthogonally to their
    common mean. Under white noise they are unit-variance, independent of each other and
    of the gyro fit's own equations, and constant-rate physics does not reach them (only
    what varies within a position: temperature, the measured specific force); under a
    wandering bias they carry its short-tau spectrum, which the ~80 equations do not
    (the Cramer-Rao bound of a figure drops from ~0.18 to ~0.13, relative)."""

    def __init__(self, prob, rec):
        from scipy.linalg import null_space

        from calib_cli.model.kinematics import Kinematics

        t = rec.time - rec.time[0]
        piece = (t // PIECE_S).astype(int)
        span = np.zeros(len(t), bool)
        inside = np.zeros(len(t), bool)
        for s in prob.statics:
            span[s.start:s.stop] = True
            inside[s.start + 1:s.stop - 1] = True
        full = np.bincount(piece, weights=span) == np.bincount(piece)
        count = np.bincount(piece, weights=inside)  # the samples each piece's mean uses
        self.groups = []  # (pieces, Q (k-1, k), static index)
        for k, s in enumerate(prob.statics):
            ps = np.unique(piece[s.start:s.stop])
            ps = ps[full[ps]]
            if len(ps) >= 2:
                self.groups.append((ps, null_space(np.sqrt(count[ps])[None, :]).T, k))
        self.sig = np.asarray(prob.sig_gyro, float)
        self.n_rows = 3 * sum(len(ps) - 1 for ps, _, _ in self.groups)
        if not self.groups:
            return
        ps = np.concatenate([g[0] for g in self.groups])
        owner = np.concatenate([np.full(len(g[0]), g[2]) for g in self.groups])
        sel = np.isin(piece, ps) & inside
        pos = np.searchsorted(ps, piece[sel])  # the statics are sorted: ps increases
        n = count[ps].astype(float)

        def mean_of(x):
            return np.stack([np.bincount(pos, weights=x[sel, c], minlength=len(ps))
                             for c in range(x.shape[1])], axis=1) / n[:, None]

        self.sqrt_n = np.sqrt(n)
        self.W = mean_of(np.asarray(rec.gyro, float))
        temp = None
        if rec.temp is not None and np.all(np.isfinite(rec.temp)):
            temp = mean_of(np.asarray(rec.temp, float)[:, None])[:, 0]
        m = len(ps)
        self.kin = Kinematics(np.zeros(m), mean_of(prob.f_all), prob.we_static[owner],
                              np.zeros((m, 3)), temp=temp)
        self.kin_no_temp = Kinematics(np.zeros(m), self.kin.f, self.kin.w, np.zeros((m, 3)))

    def residuals(self, model, p) -> np.ndarray:
        """The contrast rows (n_rows,) of the pieces' means against the model's."""
        if not self.groups:
            return np.zeros(0)
        kin = self.kin if model.has("temperature_drift") else self.kin_no_temp
        z = (self.W - model.predict(p, kin, sensors=("gyro",))["gyro"]) \
            * self.sqrt_n[:, None] / self.sig
        out, i = [], 0
        for ps, Q, _ in self.groups:
            out.append((Q @ z[i:i + len(ps)]).T.ravel())  # axis-major, then contrast
            i += len(ps)
        return np.concatenate(out)

    def response(self, npc: int) -> np.ndarray:
        """(n_rows, npc, 3): the rows' response to a bias held over each piece, per axis."""
        J = np.zeros((self.n_rows, npc, 3))
        row, i = 0, 0
        for ps, Q, _ in self.groups:
            w = Q * self.sqrt_n[i:i + len(ps)]
            for c in range(3):
                J[row:row + len(Q)][:, ps, c] = w / self.sig[c]
                row += len(Q)
            i += len(ps)
        return J


class WanderLikelihood:
    """The gyro equations of a record under a wandering bias (module docstring)."""

    def __init__(self, rec, acc, structure: str = "full"):
        from calib_cli.methods import gyro as G

        self.G, self.rec, self.structure = G, rec, structure
        self.prob = G.GyroProblem(rec, acc)
        self.M = None  # {kind: (3, n_eq, n_eq)} per unit figure^2
        self.sub = SubMeans(self.prob, rec)
        self.n0 = None  # the gyro fit's own equations: the first n0 rows

    # -- the linearised deterministic model --------------------------------
    def linear(self, names, res):
        """(r, A) at the white fit ``res`` of base + ``names``: whitened residuals and
        their Jacobian over the model's free parameters."""
        from calib_cli.methods.with_effects import gyro_effect
        from calib_cli.model.imu_model import Packing

        extra = tuple(gyro_effect(n) for n in names if n != "g_sensitivity")
        model = self.G.gyro_model("g_sensitivity" in names or bool(res.stats.get("g_sensitivity")),
                                  extra, self.structure)
        packing = Packing.for_model(model)
        base = model.neutral_params()
        p = {k: np.asarray(res.params.get(k, v), float) for k, v in base.items()}
        sig = self.prob.sigmas(model, p)
        theta = packing.pack(p)

        def rows(q):
            return np.concatenate([self.prob.residuals(model, q, sig),
                                   self.sub.residuals(model, q)])

        r = rows(p)
        A = np.empty((len(r), packing.size))
        for j in range(packing.size):
            th = theta.copy()
            h = 1e-6 * max(1e-3, abs(th[j]))
            th[j] += h
            A[:, j] = (rows(packing.unpack(th, base)) - r) / h
        if self.M is None:
            self.n0 = len(r) - self.sub.n_rows
            self._response(model, p, sig, r[:self.n0])
        return r, A, packing.labels()

    def _response(self, model, p, sig, r0):
        """M per kind and axis, from J at the first model (J hardly depends on it)."""
        prob, rec = self.prob, self.rec
        t = rec.time - rec.time[0]
        piece = (t // PIECE_S).astype(int)
        npc = int(piece.max()) + 1
        gy0 = np.asarray(rec.gyro, float)
        h = float(np.mean(prob.sig_gyro)) or 1e-6
        # each equation sees the data over its own window (a static position, a
        # transition, a turn): pieces K apart never share one, so a bias held over
        # every K-th piece at once gives each equation's response to its own piece
        win = [(s.start, s.stop) for s in prob.statics for _ in range(3)]
        win += [(a, b + 1) for _, a, b in prob.transitions for _ in range(2)]
        win += [(s.start, s.stop) for s in prob.turns for _ in range(3)]
        first = np.array([piece[a] for a, _ in win])
        last = np.array([piece[b - 1] for _, b in win])
        K = int((last - first).max()) + 2
        J = np.zeros((len(r0), npc, 3))
        w0 = prob.W_static.copy()
        try:
            for c in range(min(K, npc)):
                m = piece % K == c
                for ax in range(3):
                    gy = gy0.copy()
                    gy[m, ax] += h
                    prob.rec = rec.with_(gyro=gy)
                    prob.W_static = np.array([gy[s.slice].mean(axis=0)
                                              for s in prob.statics]).reshape(-1, 3)
                    dr = (prob.residuals(model, p, sig) - r0) / h
                    for i in range(len(r0)):
                        j = first[i] + (c - first[i]) % K  # the window's piece of colour c
                        if j <= last[i]:
                            J[i, j, ax] = dr[i]
        finally:
            prob.rec, prob.W_static = rec, w0
        self.J = np.concatenate([J, self.sub.response(npc)], axis=0)
        self.M = {k: self.response(piece_cov(k, npc, PIECE_S)) for k in KEYS}
        # a figure scale per kind for the profile's grid (data units)
        span = max(float(t[-1]), PIECE_S)
        white = float(np.mean(prob.sig_gyro))
        self.scale = {"bias_random_walk": white / np.sqrt(span),
                      "bias_instability": white}

    def response(self, C):
        """M per axis (3, n_eq, n_eq) of a bias process with piece covariance C."""
        return np.stack([self.J[:, :, ax] @ C @ self.J[:, :, ax].T for ax in range(3)])

    # -- the likelihood ------------------------------------------------------
    def m2ll(self, r, A, kind=None, x=None, reml: bool = False):
        """(-2 log L, whitened residuals at the GLS optimum, V) with figures x (3,);
        reml: the restricted likelihood (+ log det A^T V^-1 A), whose maximum does not
        shrink the figures by the deterministic parameters fitted beside them."""
        n = len(r)
        V = np.eye(n)
        if kind is not None:
            V = V + np.tensordot(np.asarray(x, float) ** 2, self.M[kind], axes=1)
        L = cholesky(V, lower=True, check_finite=False)
        # L is triangular: a triangular solve, not a general one (half the run time)
        w = solve_triangular(L, np.column_stack([r, A]), lower=True, check_finite=False)
        rw, Aw = w[:, 0], w[:, 1:]
        d, *_ = np.linalg.lstsq(Aw, rw, rcond=None)
        e = rw - Aw @ d
        m2 = float(e @ e + 2.0 * np.log(np.diag(L)).sum())
        if reml:
            m2 += float(np.linalg.slogdet(Aw.T @ Aw)[1])
        return m2, e, V

    def profile(self, r, A, kind, reml: bool = True):
        """Figures x (3,) maximising the restricted likelihood (reml=False: the
        likelihood), their rough sigma (curvature of that -2 log L), -2 log L (not
        restricted) and the whitened residuals there."""
        from scipy.optimize import minimize_scalar

        def f(y):
            return self.m2ll(r, A, kind, y, reml=reml)[0]

        s0 = self.scale[kind]
        grid = s0 * np.logspace(-3, 1, 33)
        vals = [f([g, g, g]) for g in grid]
        x = np.full(3, grid[int(np.argmin(vals))])
        for _ in range(2):
            for ax in range(3):
                def g(u, ax=ax):
                    y = x.copy()
                    y[ax] = np.exp(u)
                    return f(y)

                lo = np.log(max(x[ax], 1e-3 * s0))
                o = minimize_scalar(g, bounds=(lo - 2.5, lo + 2.5), method="bounded",
                                    options={"xatol": 0.01})
                y = x.copy()
                y[ax] = 0.0
                x[ax] = 0.0 if f(y) <= o.fun else float(np.exp(o.x))
        sig = np.full(3, np.nan)
        for ax in range(3):
            if x[ax] <= 0:
                continue
            h = 0.1 * x[ax]
            v = []
            for dx in (-h, 0.0, h):
                y = x.copy()
                y[ax] += dx
                v.append(f(y))
            c2 = (v[0] - 2 * v[1] + v[2]) / h ** 2
            if c2 > 0:
                sig[ax] = float(np.sqrt(2.0 / c2))
        m2, e, V = self.m2ll(r, A, kind, x)
        return x, sig, m2, e, V

    # -- the final model ----------------------------------------------------
    def result(self, res, labels, A, e, V, kind, x, sig):
        """The white fit's result with the wander as a noise-model term: sandwich
        covariance of its gyro entries, the whitened residual as chi^2."""
        n0 = self.n0  # the white fit's estimator uses its own equations only
        A, V, e = A[:n0], V[:n0, :n0], e[:n0]
        N = A.T @ A
        Ni = np.linalg.pinv(N)
        C = Ni @ A.T @ V @ A @ Ni
        cov = np.array(res.covariance, float, copy=True)
        order = {tuple(k): i for i, k in enumerate(res.cov_order)}
        idx = [order.get((k, int(i))) for k, i in labels]
        sigma = {k: np.array(v, float, copy=True) for k, v in res.sigma.items()}
        for a, ia in enumerate(idx):
            if ia is None:
                continue
            for b, ib in enumerate(idx):
                if ib is not None:
                    cov[ia, ib] = C[a, b]
            k, i = labels[a]
            if k in sigma and np.isfinite(sigma[k].reshape(-1)[i]):
                sigma[k].reshape(-1)[i] = np.sqrt(max(C[a, a], 0.0))
        st = dict(res.stats)
        chi2 = float(e @ e)
        st["chi2"] = chi2
        st["chi2_dof"] = chi2 / max(int(st.get("dof", 1)), 1)
        st["sigma_inflation"] = 1.0
        key = KEYS[kind]
        nm = dict(st.get("noise_model", {}))
        nm[f"gyro {kind}"] = {"params": {key: np.asarray(x, float).tolist()},
                              "sigma": {key: np.asarray(sig, float).tolist()}, "note": NOTE}
        st["noise_model"] = nm
        return replace(res, covariance=cov, sigma=sigma, stats=st)


def unit_of(res) -> float:
    """Data units per rad/s (the mean of diag gyro_K): the wander's figures in SI."""
    return abs(float(np.mean(np.diag(np.asarray(res.params["gyro_K"], float))))) or 1.0


def with_wander(W: WanderLikelihood, lin, res, kind: str):
    """The white fit ``res`` (linearised as ``lin`` = W.linear(names, res)) with the
    wander ``kind`` as its noise-model term: (result, figures, sigma), the figures in data
    units (the restricted-likelihood maximum). ``fit gyro --with`` and the diagnosis's
    final model are both this computation."""
    r, A, labels = lin
    x, sig, _, e, V = W.profile(r, A, kind)
    u = unit_of(res)
    return W.result(res, labels, A, e, V, kind, x / u, sig / u), x, sig
