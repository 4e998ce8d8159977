"""The objective functions of the SMU package (Structural Model Updating, Wang et al.,
GPL-3.0), reimplemented on boltwatch's fixtures `tests/data/smu-*`, to check that the
fixtures reproduce the published best fits.

Not boltwatch and not SMU code: numpy and scipy read a fixture's `model.json` (K(θ) =
Σ θ_l K_l, θ_l = 1 + α_l of SMU), `data.json` (the measured shapes) and `published.json`
(λ^exp as SMU uses it, the reference entries q_i and the weights), and evaluate

- form 1 (MAC value):  f = Σ_i [w_λi (λ_i^exp − λ_i) / λ_i^exp]² + [w_ψi (1 − √MAC_i) / √MAC_i]²
- form 2 (eigenvector difference):
      f = Σ_i [w_λi (λ_i^exp − λ_i) / λ_i^exp]² + w_ψi² Σ_{k ≠ q_i} (ψ_ki^exp − ψ_ki / ψ_{q_i,i})²
- form 3 (modal dynamic residual, four-storey case only):
      f = Σ_i w_i² ‖(K(θ) − λ_i^exp M) [ψ_i^exp; ψ_i^U]‖², with the given unmeasured entries
      ψ^U, or minimized over them (exact least squares) when none are given,

where λ_i, ψ_i are the i-th lowest eigenpair of K(θ) ψ = λ M ψ (the i-th experimental mode
is paired with the i-th model mode, SMU's modeMatch = 2) and ψ_i is taken at the channels.
Massless DOFs are condensed out statically (dense: the footbridge's 946 DOFs take ~0.4 s).

usage: python3 tests/python/smu_objective.py [CASE ...]   (footbridge, four-storey, shear-18)
prints, per case: frequencies and MACs at nominal and published θ, and every published
fit's objective against its reimplementation here.
"""

import json
import os
import sys

import numpy as np
import scipy.io
import scipy.linalg

DATA = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "data")
_CACHE = {}


class Case:
    def __init__(self, name):
        d = os.path.join(DATA, name if name.startswith("smu-") else f"smu-{name}")
        model = json.load(open(os.path.join(d, "model.json")))
        data = json.load(open(os.path.join(d, "data.json")))
        self.published = json.load(open(os.path.join(d, "published.json")))
        self.names = [p["name"] for p in model["parameters"]]
        self.Kj = [self._mtx(os.path.join(d, p["file"])) for p in model["parameters"]]
        self.K0 = self._mtx(os.path.join(d, model["k0"])) if model.get("k0") else 0.0
        self.M = self._mtx(os.path.join(d, model["mass"]))
        channel_dof = {c["name"]: c["dofs"][0][0] for c in model["channels"]}
        self.meas = np.array([channel_dof[c] for c in data["channels"]])
        self.psi_exp = np.array([m["shape"] for m in data["modes"]]).T
        obj = self.published["objective"]
        self.lam_exp = np.array(obj["lambda_exp"])
        self.q = obj["reference_entry_q"]
        assert all(self.psi_exp[q, i] == 1.0 for i, q in enumerate(self.q))
        self.forms = {k: v for k, v in obj.items() if k.startswith("form")}
        self.primary = next(f["formulation"] for f in self.published["fits"] if f["primary"])

    @staticmethod
    def _mtx(path):
        a = scipy.io.mmread(path)
        return np.asarray(a.toarray() if hasattr(a, "toarray") else a, dtype=float)

    def stiffness(self, theta):
        return self.K0 + sum(t * k for t, k in zip(theta, self.Kj))

    def modes(self, theta, n):
        """The n lowest eigenpairs (λ, ψ at every DOF), massless DOFs condensed out."""
        K, m = self.stiffness(theta), np.diag(self.M)
        a, s = np.where(m > 0)[0], np.where(m == 0)[0]
        if len(s):
            X = np.linalg.solve(K[np.ix_(s, s)], K[np.ix_(s, a)])
            Kc = K[np.ix_(a, a)] - K[np.ix_(a, s)] @ X
        else:
            X, Kc = None, K
        lam, V = scipy.linalg.eigh(Kc, np.diag(m[a]), subset_by_index=[0, min(n, len(a)) - 1])
        phi = np.zeros((len(m), V.shape[1]))
        phi[a] = V
        if len(s):
            phi[s] = -X @ V
        return lam, phi


def case(name):
    if name not in _CACHE:
        _CACHE[name] = Case(name)
    return _CACHE[name]


def mac(a, b):
    return float((a @ b) ** 2 / ((a @ a) * (b @ b)))


def published_objective(theta, case_name="footbridge", form=None, psi_unmeasured=None):
    """SMU's objective at θ (θ_l = 1 + α_l) for the case's formulation `form`
    (default: its primary fit's)."""
    c = case(case_name)
    form = form or c.primary
    spec = c.forms[form]
    theta = np.asarray(theta, dtype=float)
    n_modes = len(c.lam_exp)
    if form.startswith("form3"):
        K = c.stiffness(theta)
        un = np.setdiff1d(np.arange(K.shape[0]), c.meas)
        total = 0.0
        for i in range(n_modes):
            A = K - c.lam_exp[i] * c.M
            b = A[:, c.meas] @ c.psi_exp[:, i]
            if psi_unmeasured is None:
                u, *_ = np.linalg.lstsq(A[:, un], -b, rcond=None)
            else:
                u = np.asarray(psi_unmeasured, dtype=float)[i * len(un):(i + 1) * len(un)]
            total += spec["weights"][i] ** 2 * float(np.sum((A[:, un] @ u + b) ** 2))
        return total
    lam, phi = c.modes(theta, n_modes)
    total = 0.0
    for i in range(n_modes):
        psi = phi[c.meas, i] / phi[c.meas[c.q[i]], i]
        total += (spec["lambda_weights"][i] * (c.lam_exp[i] - lam[i]) / c.lam_exp[i]) ** 2
        if form.startswith("form1"):
            m = mac(c.psi_exp[:, i], psi)
            total += (spec["psi_weights"][i] * (1 - np.sqrt(m)) / np.sqrt(m)) ** 2
        else:
            keep = np.arange(len(c.meas)) != c.q[i]
            total += spec["psi_weights_applied"][i] ** 2 * float(np.sum((c.psi_exp[keep, i] - psi[keep]) ** 2))
    return total


def report(name):
    c = case(name)
    n_modes = len(c.lam_exp)
    f_meas = np.sqrt(c.lam_exp) / (2 * np.pi)
    print(f"== smu-{name}: {c.M.shape[0]} DOFs ({int(np.sum(np.diag(c.M) == 0))} massless), "
          f"{len(c.Kj)} parameters, {n_modes} modes on {len(c.meas)} channels")
    print("  measured f [Hz]:", np.array2string(f_meas, precision=5))
    for label, theta in [("nominal", np.ones(len(c.Kj)))] + [
            (f"published {f['formulation']}", np.array(f["theta"])) for f in c.published["fits"]]:
        lam, phi = c.modes(theta, n_modes + 3)
        f = np.sqrt(lam) / (2 * np.pi)
        macs = [mac(c.psi_exp[:, i], phi[c.meas, i]) for i in range(n_modes)]
        print(f"  {label}: f [Hz] {np.array2string(f, precision=5)}")
        print(f"  {' ' * len(label)}  MAC(exp i, model i) {np.array2string(np.array(macs), precision=4)}")
    for fit in c.published["fits"]:
        form = fit["formulation"]
        at_nominal = published_objective(np.ones(len(c.Kj)), name, form)
        ours = published_objective(fit["theta"], name, form, fit.get("psi_unmeasured"))
        line = (f"  {form}: published {fit['objective']:.12g}, here {ours:.12g} "
                f"(rel {ours / fit['objective'] - 1:+.2e}); at nominal θ {at_nominal:.6g}")
        if form.startswith("form3"):
            line += f"; profiled over ψ^U at published θ {published_objective(fit['theta'], name, form):.12g}"
        print(line)


if __name__ == "__main__":
    for name in sys.argv[1:] or ["footbridge", "four-storey", "shear-18"]:
        report(name)
