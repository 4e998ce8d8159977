#!/usr/bin/env python3
"""Converts three measured model-updating cases of the SMU package (Structural Model
Updating, https://github.com/ywang-structures/Structural-Model-Updating, GPL-3.0) into
boltwatch fixtures: `tests/data/smu-footbridge`, `tests/data/smu-four-storey` and
`tests/data/smu-shear-18`.

usage: smu-convert.py SMU [OUT_DIR]

SMU is a checkout of that repository or its bare git directory (then the files are read
with `git show HEAD:<path>`); OUT_DIR defaults to the directory of this script. Needs
numpy and scipy (scipy.io.loadmat reads the MAT-files, all MATLAB v5).

Per case it writes `model.json` (boltwatch.matrices.v1), `K_<param>.mtx` and `M.mtx`
(Matrix Market, coordinate real symmetric, lower triangle, 17 significant digits, exact
zeros dropped), `dofs.txt`, `data.json` (boltwatch.modal_set.v1: the measured modes the
case uses, with the uncertainties it publishes or its objective's weights imply),
`published.json` (the published best fits, their objective's definition and weights, and
frequencies / MACs at the published and nominal θ, computed here) and nothing else; the
README.md of each case is written by hand.

Parameterization. SMU writes K(α) = K0 + Σ_j α_j K_j with α_j the relative change of
parameter j (α = 0 nominal), and in all three cases K0 = Σ_j K_j exactly (that is how
their scripts build it). boltwatch writes K(θ) = K0' + Σ_l θ_l K_l' with θ = 1 nominal, so
K_l' = K_j, θ_l = 1 + α_l and K0' = K0 − Σ_j K_j = 0: `"k0": null` (no K0 file). Bounds
α ∈ [lo, hi] become θ ∈ [1 + lo, 1 + hi].
"""

import io
import json
import os
import subprocess
import sys

import numpy as np
import scipy.io
import scipy.linalg

REPO_URL = "https://github.com/ywang-structures/Structural-Model-Updating"


# ---------------------------------------------------------------------------------------
# Reading the SMU repository (checkout or bare git directory)
# ---------------------------------------------------------------------------------------


class Source:
    def __init__(self, root):
        self.root = root
        self.bare = not os.path.isdir(os.path.join(root, "Examples"))
        self.commit = self._git("rev-parse", "HEAD").decode().strip()

    def _git(self, *args):
        flag = ["--git-dir", self.root] if self.bare else ["-C", self.root]
        return subprocess.run(["git", *flag, *args], check=True, capture_output=True).stdout

    def read(self, path):
        if self.bare:
            return self._git("show", f"HEAD:{path}")
        with open(os.path.join(self.root, path), "rb") as f:
            return f.read()

    def mat(self, path):
        return scipy.io.loadmat(io.BytesIO(self.read(path)), struct_as_record=False, squeeze_me=True)


def dense(a):
    return np.asarray(a.toarray() if hasattr(a, "toarray") else a, dtype=float)


# ---------------------------------------------------------------------------------------
# Writing
# ---------------------------------------------------------------------------------------


def write_mtx(path, a, comment):
    a = np.asarray(a, dtype=float)
    assert np.array_equal(a, a.T), path
    i, j = np.nonzero(np.tril(a))
    order = np.lexsort((i, j))  # column-major, as Matrix Market writers usually do
    i, j = i[order], j[order]
    n = a.shape[0]
    with open(path, "w") as f:
        f.write("%%MatrixMarket matrix coordinate real symmetric\n")
        f.write(f"% {comment}\n")
        f.write(f"{n} {n} {len(i)}\n")
        for r, c in zip(i, j):
            f.write(f"{r + 1} {c + 1} {a[r, c]:.17g}\n")


def _dumps(obj, level=0):
    """JSON with one key per line and lists of numbers (or of short lists) on one line."""
    pad, inner = " " * level, " " * (level + 1)
    if isinstance(obj, dict):
        if not obj:
            return "{}"
        items = [f"{inner}{json.dumps(k, ensure_ascii=False)}: {_dumps(v, level + 1)}" for k, v in obj.items()]
        return "{\n" + ",\n".join(items) + "\n" + pad + "}"
    if isinstance(obj, list):
        flat = all(not isinstance(v, (dict, list)) for v in obj)
        pairs = all(isinstance(v, list) and all(not isinstance(w, (dict, list)) for w in v) and len(v) <= 2 for v in obj)
        if flat or (pairs and obj):
            return json.dumps(obj, ensure_ascii=False)
        return "[\n" + ",\n".join(inner + _dumps(v, level + 1) for v in obj) + "\n" + pad + "]"
    return json.dumps(obj, ensure_ascii=False)


def write_json(path, obj):
    text = _dumps(obj)
    assert json.loads(text) == obj
    with open(path, "w") as f:
        f.write(text + "\n")


def num(x):
    """A float for JSON: shortest repr that round-trips."""
    return float(x)


# ---------------------------------------------------------------------------------------
# Modal computations (dense; massless DOFs by static condensation)
# ---------------------------------------------------------------------------------------


def eigen(Kj, M, theta, n):
    K = sum(t * k for t, k in zip(theta, Kj))
    m = np.diag(M)
    assert np.array_equal(M, np.diag(m))
    a, s = np.where(m > 0)[0], np.where(m == 0)[0]
    if len(s):
        X = np.linalg.solve(K[np.ix_(s, s)], K[np.ix_(s, a)])
        Kc = K[np.ix_(a, a)] - K[np.ix_(a, s)] @ X
    else:
        Kc = K
    lam, V = scipy.linalg.eigh(Kc, np.diag(m[a]), subset_by_index=[0, n - 1])
    phi = np.zeros((len(m), n))
    phi[a] = V
    if len(s):
        phi[s] = -X @ V
    return lam, phi


def mac(a, b):
    return float((a @ b) ** 2 / ((a @ a) * (b @ b)))


def fit_summary(Kj, M, theta, meas, psi_exp, n_extra=3):
    n_modes = psi_exp.shape[1]
    n_mass = int(np.count_nonzero(np.diag(M)))
    lam, phi = eigen(Kj, M, theta, min(n_modes + n_extra, n_mass))
    f = np.sqrt(lam) / (2 * np.pi)
    macs = [mac(psi_exp[:, i], phi[meas, i]) for i in range(n_modes)]
    return [num(x) for x in f], [num(x) for x in macs]


# ---------------------------------------------------------------------------------------
# Shared pieces of a case
# ---------------------------------------------------------------------------------------


def write_model(out, structure, labels, Kj, names, kinds, M, lo, hi, channels, note):
    os.makedirs(out, exist_ok=True)
    for fn in os.listdir(out):
        if fn.endswith(".mtx"):
            os.remove(os.path.join(out, fn))
    n = M.shape[0]
    params = []
    for name, kind, K, a, b in zip(names, kinds, Kj, lo, hi):
        fn = f"K_{name}.mtx"
        write_mtx(os.path.join(out, fn), K, f"{structure}: K_{name} = dK/dtheta_{name} ({note})")
        params.append({"name": name, "nominal": 1.0, "lower": num(round(1.0 + a, 12)),
                       "upper": num(round(1.0 + b, 12)), "file": fn, "kind": kind})
    write_mtx(os.path.join(out, "M.mtx"), M, f"{structure}: mass matrix ({note})")
    with open(os.path.join(out, "dofs.txt"), "w") as f:
        f.write("\n".join(labels) + "\n")
    files = ["dofs.txt", "M.mtx"] + [p["file"] for p in params]
    write_json(os.path.join(out, "model.json"), {
        "schema": "boltwatch.matrices.v1",
        "structure": structure,
        "n_dof": n,
        "stiffness": "K(θ) = Σ θ_l K_l (no K0: the SMU case's K0 equals Σ K_l, θ_l = 1 + α_l)",
        "files": files,
        "k0": None,
        "mass": "M.mtx",
        "dofs": "dofs.txt",
        "parameters": params,
        "channels": [{"name": c, "dofs": [[int(d), 1.0]]} for c, d in channels],
    })


def modal_set(structure, time, channels, freqs, covs, shapes, stds=None, damping=None, source=""):
    modes = []
    for i, f in enumerate(freqs):
        m = {"frequency_hz": num(f), "frequency_cov": num(covs[i]),
             "shape": [num(x) for x in shapes[:, i]]}
        if stds is not None:
            m["shape_std"] = [num(x) for x in stds[:, i]]
        if damping is not None:
            m["damping_ratio"] = num(damping[i])
        modes.append(m)
    return {"schema": "boltwatch.modal_set.v1", "structure": structure, "time": time,
            "channels": list(channels), "modes": modes, "source": source}


def run_stats(fval, exit_flag):
    fval = np.atleast_1d(fval).astype(float)
    k = int(np.argmin(fval))
    best = fval[k]
    flags, counts = np.unique(np.atleast_1d(exit_flag).astype(int), return_counts=True)
    return k, {
        "starts": int(len(fval)),
        "runs_within_1e-6_rel_of_best": int(np.sum(fval <= best * (1 + 1e-6))),
        "runs_within_1e-3_rel_of_best": int(np.sum(fval <= best * (1 + 1e-3))),
        "exit_flags": {str(a): int(b) for a, b in zip(flags, counts)},
    }


def fit_entry(fid, primary, path, algorithm, R, key, n_alpha, names, lo, hi, Kj, M, meas, psi_exp, extra=None):
    k, stats = run_stats(R["fval"], R["exit_flag"])
    x = np.asarray(R[key], dtype=float)[:, k]
    alpha = x[:n_alpha]
    theta = 1.0 + alpha
    f, macs = fit_summary(Kj, M, theta, meas, psi_exp)
    at_lower = [n for n, a, b in zip(names, alpha, lo) if abs(a - b) <= 1e-6 * max(1.0, abs(b))]
    at_upper = [n for n, a, b in zip(names, alpha, hi) if abs(a - b) <= 1e-6 * max(1.0, abs(b))]
    e = {
        "formulation": fid,
        "primary": primary,
        "result_file": path,
        "algorithm": algorithm,
        "best_run": k + 1,
        "objective": num(R["fval"][k]),
        "alpha": [num(a) for a in alpha],
        "theta": [num(t) for t in theta],
        "at_lower_bound": at_lower,
        "at_upper_bound": at_upper,
        **stats,
        "discarded_out_of_bounds_runs": int(np.count_nonzero(np.atleast_1d(R["t_waste"]))),
        "frequencies_hz_computed": f,
        "mac_computed": macs,
    }
    if extra:
        e.update(extra(x))
    return e


# ---------------------------------------------------------------------------------------
# Case 1: steel pedestrian bridge (SAP2000 model, 946 DOFs)
# ---------------------------------------------------------------------------------------

FB = "Examples/SteelPedestrianBridge/Experiment/Experiment_Model_Updating"
# Channel directions read off Examples/SteelPedestrianBridge/Experiment/Figure/PsiEntry.png
# and SapEntry.png (green arrows y = lateral, red z = vertical); the support springs
# K_y1, K_z1, K_y2, K_z2 sit on DOFs 17/21, 13/22, 572/854, 571/852 (1-based), which
# those figures mark y, z, y, z: consistent.
FB_DIRS = "yzyzyzyzy" + "yz" * 22 + "yzyyz"


def footbridge(src, out):
    s = src.mat(f"{FB}/SteelPedestrianBridgeExp.mat")
    e = src.mat(f"{FB}/ExpModeInfo_FEM.mat")
    their = ["K_Frame", "K_Truss"] + [f"K_Conc{i}" for i in range(1, 12)] + ["K_y1", "K_z1", "K_y2", "K_z2"]
    names = ["frame", "truss"] + [f"deck{i:02d}" for i in range(1, 12)] + ["spring_y1", "spring_z1", "spring_y2", "spring_z2"]
    kinds = ["matrix"] * 13 + ["spring"] * 4
    Kj = [dense(s[n]) for n in their]
    M = dense(s["M0"])
    n = M.shape[0]
    meas = np.asarray(s["measDOFs"], dtype=int).ravel() - 1
    assert len(meas) == 58 and len(FB_DIRS) == 58
    lo = [-0.1] * 2 + [-0.2] * 11 + [-1.0] * 4   # SteelPedestrianBridge_Exp.m, formID < 3
    hi = [0.1] * 2 + [0.4] * 11 + [10.0] * 4

    lam_exp = np.asarray(e["lambdaExp"], dtype=float).ravel()
    psi = np.asarray(e["psiExp_m"], dtype=float)
    std_psi = np.asarray(e["std_psiExp"], dtype=float)
    std_lam = np.asarray(e["std_lambdaExp"], dtype=float).ravel()
    n_modes = len(lam_exp)
    q = [int(np.flatnonzero(psi[:, i] == 1)[0]) for i in range(n_modes)]

    # Result files: check they were run on these very matrices and data.
    R1 = src.mat(f"{FB}/Results/SteelPedBridg_form1_JAConinterior-point.mat")
    R2 = src.mat(f"{FB}/Results/SteelPedBridg_form2_JAConinterior-point.mat")
    for R in (R1, R2):
        sm, em = R["structModel"], R["expModes"]
        assert np.array_equal(dense(sm.K0), sum(Kj)), "their K0 is Σ K_j"
        assert all(np.array_equal(dense(sm.K_j[j]), Kj[j]) for j in range(17))
        assert np.array_equal(dense(sm.M0), M)
        assert np.array_equal(em.psiExp, psi) and np.array_equal(np.ravel(em.lambdaExp), lam_exp)
        assert np.allclose(np.ravel(R["updatingOpts"].x_lb), lo) and np.allclose(np.ravel(R["updatingOpts"].x_ub), hi)
    w_lam = np.ravel(R1["expModes"].lambdaWeights)
    assert np.allclose(w_lam, lam_exp / std_lam, rtol=1e-14)
    w_psi1 = np.ravel(R1["expModes"].psiWeights)
    w_psi2_matrix = np.asarray(R2["expModes"].psiWeights)
    # MATLAB linear indexing psiWeights(i) of the 58×5 matrix: entry (i, 1).
    w_psi2 = w_psi2_matrix.ravel(order="F")[:n_modes]
    assert np.allclose(w_psi2, 1 / std_psi[:n_modes, 0] / 58, rtol=1e-14)

    labels = [f"eq{k + 1}" for k in range(n)]
    channels = [(f"ch{c + 1:02d}-{FB_DIRS[c]}", d) for c, d in enumerate(meas)]
    note = "SMU SteelPedestrianBridgeExp.mat, SAP2000 export; units as exported (not stated)"
    write_model(out, "smu-footbridge", labels, Kj, names, kinds, M, lo, hi, channels, note)

    std_shape = std_psi.copy()
    for i, qi in enumerate(q):
        assert std_shape[qi, i] < 1e-15
        std_shape[qi, i] = 0.0  # the reference entry: ~1e-16 in the file (0 by construction)
    freqs = np.sqrt(lam_exp) / (2 * np.pi)
    write_json(os.path.join(out, "data.json"), modal_set(
        "smu-footbridge", "2019-01-20T10:59:00Z", [c for c, _ in channels], freqs,
        0.5 * std_lam / lam_exp, psi, std_shape,
        source=f"SMU {FB}/ExpModeInfo_FEM.mat @ {src.commit[:12]}: 5 modes identified on 58 "
               "channels (frequency_cov = std_lambdaExp / (2 lambdaExp); shape_std = std_psiExp, "
               "0 at the reference entry); time = the MAT-file's creation time, not the test's"))

    fits = [
        fit_entry("form1_mac", False, f"{FB}/Results/SteelPedBridg_form1_JAConinterior-point.mat",
                  "fmincon interior-point, analytical gradient, tolFun = tolX = 1e-10",
                  R1, "alpha", 17, names, lo, hi, Kj, M, meas, psi),
        fit_entry("form2_eigenvector_difference", True, f"{FB}/Results/SteelPedBridg_form2_JAConinterior-point.mat",
                  "fmincon interior-point, analytical gradient, tolFun = tolX = 1e-10",
                  R2, "x", 17, names, lo, hi, Kj, M, meas, psi),
    ]
    f0, mac0 = fit_summary(Kj, M, np.ones(17), meas, psi)
    write_json(os.path.join(out, "published.json"), {
        "case": "smu-footbridge",
        "source": {
            "repository": REPO_URL, "commit": src.commit, "license": "GPL-3.0",
            "files": [f"{FB}/SteelPedestrianBridge_Exp.m", f"{FB}/LoadStructure.m",
                      f"{FB}/SteelPedestrianBridgeExp.mat", f"{FB}/ExpModeInfo_FEM.mat",
                      f"{FB}/Results/SteelPedBridg_form1_JAConinterior-point.mat",
                      f"{FB}/Results/SteelPedBridg_form2_JAConinterior-point.mat",
                      "SMU/StructModelUpdating.m", "SMU/OptmzObjJac.m",
                      "SMU/ModelUpdatingObjective.m", "SMU/ObjFuncMPDLsqnonlin.m", "SMU/MAC.m",
                      "SMU/MultiRunModelUpdating.m"],
            "not_available": f"{FB}/Results/SteelPedBridg_form3_JACon_trust-region-reflective.mat "
                             "(modal dynamic residual; the blob is absent from the snapshot)",
        },
        "parameterization": "SMU: K(α) = K0 + Σ α_j K_j, K0 = Σ K_j (α = 0 nominal). Here: "
                            "K(θ) = Σ θ_l K_l, θ_l = 1 + α_l; bounds θ = 1 + α bounds.",
        "parameters": names,
        "alpha_lower": lo, "alpha_upper": hi,
        "theta_lower": [num(round(1 + a, 12)) for a in lo],
        "theta_upper": [num(round(1 + b, 12)) for b in hi],
        "objective": {
            "eigenproblem": "K(θ) ψ = λ M ψ (474 massless DOFs: MATLAB eigs(K, M, 5, 'sm')); "
                            "experimental mode i is paired with the i-th lowest model mode "
                            "(modeMatch = 2, no MAC matching)",
            "lambda_exp": [num(x) for x in lam_exp],
            "reference_entry_q": q,
            "reference_entry_rule": "q_i = the channel (0-based) where psiExp(:, i) == 1 exactly "
                                    "(SMU/StructModelUpdating.m); the model shape at the channels is "
                                    "divided by its q_i-th entry. Not always the largest |entry|: "
                                    "modes 2, 4, 5 have entries of magnitude 1.025, 1.014, 1.312.",
            "form1_mac": {
                "formula": "f(α) = Σ_i [w_λi (λ_i^exp − λ_i(α)) / λ_i^exp]² + [w_ψi (1 − √MAC_i) / √MAC_i]², "
                           "MAC_i = (ψ_i^exp·ψ_i)² / (|ψ_i^exp|² |ψ_i|²) at the 58 channels",
                "lambda_weights": [num(x) for x in w_lam],
                "lambda_weights_rule": "w_λi = λ_i^exp / σ_λi (std_lambdaExp): the term is (λ_i^exp − λ_i) / σ_λi",
                "psi_weights": [num(x) for x in w_psi1],
                "psi_weights_rule": "w_ψi = 1 / ‖std_psiExp(k ≠ q_i, i)‖₂",
            },
            "form2_eigenvector_difference": {
                "formula": "f(α) = Σ_i [w_λi (λ_i^exp − λ_i(α)) / λ_i^exp]² + w_ψi² Σ_{k ≠ q_i} "
                           "(ψ_ki^exp − ψ_ki(α) / ψ_{q_i i}(α))²",
                "lambda_weights": [num(x) for x in w_lam],
                "psi_weights_applied": [num(x) for x in w_psi2],
                "psi_weights_rule": "the script sets a 58×5 matrix psiWeights(k, i) = 1 / (58 std_psiExp(k, i)), "
                                    "but SMU/ObjFuncMPDLsqnonlin.m (and the Jacobian) multiply mode i's "
                                    "difference vector by the scalar psiWeights(i), MATLAB linear indexing = "
                                    "psiWeights(i, 1) = 1 / (58 std_psiExp(i, 1)): one weight per mode, "
                                    "taken from mode 1's first five channels. The published objective "
                                    "values are reproduced only with this applied weighting.",
            },
        },
        "frequencies_hz_measured": [num(x) for x in freqs],
        "nominal_theta": {"frequencies_hz_computed": f0, "mac_computed": mac0},
        "fits": fits,
    })


# ---------------------------------------------------------------------------------------
# Shear frames
# ---------------------------------------------------------------------------------------


def shear_kj(k):
    """SMU's influence matrices of a shear frame: K_1 the ground storey, K_j between
    floors j−1 and j (1-based), each at its nominal storey stiffness."""
    n = len(k)
    out = []
    for j in range(n):
        a = np.zeros((n, n))
        if j == 0:
            a[0, 0] = k[0]
        else:
            a[j - 1, j - 1] = a[j, j] = k[j]
            a[j - 1, j] = a[j, j - 1] = -k[j]
        out.append(a)
    return out


FS = "Examples/FourStoryStructure/Experiment"


def mdr_profile(Kj, M, theta, meas, lam_exp, psi_exp, w):
    """SMU formulation 3 minimized over the unmeasured shape entries (exact least squares),
    with those entries returned."""
    K = sum(t * k for t, k in zip(theta, Kj))
    n = M.shape[0]
    un = np.setdiff1d(np.arange(n), meas)
    total, psi_u = 0.0, []
    for i in range(len(lam_exp)):
        A = K - lam_exp[i] * M
        b = A[:, meas] @ psi_exp[:, i]
        u, *_ = np.linalg.lstsq(A[:, un], -b, rcond=None)
        total += w[i] ** 2 * float(np.sum((A[:, un] @ u + b) ** 2))
        psi_u.append(u)
    return total, psi_u


def four_storey(src, out):
    d = src.mat(f"{FS}/FourStoryStructure.mat")
    # FourStoryStructureExperiment.m: N = 4, storey stiffness 0.01 * 1000 = 10 lbf/in,
    # floor mass 12.060 lb / 386.088 in/s², measured DOFs 1-3, the lowest two modes.
    k = 0.01 * 1000 * np.ones(4)
    M = np.diag(12.060 / 386.088 * np.ones(4))
    Kj = shear_kj(k)
    meas = np.array([0, 1, 2])
    n_modes = 2
    names = [f"storey{j}" for j in range(1, 5)]
    lo, hi = [-1.0] * 4, [1.0] * 4
    f_exp = np.asarray(d["test_frequency"], dtype=float).ravel()[:n_modes]
    lam_exp = (f_exp * 2 * np.pi) ** 2
    psi = np.asarray(d["test_mode"], dtype=float)[np.ix_(meas, range(n_modes))]
    q = [int(np.argmax(np.abs(psi[:, i]))) for i in range(n_modes)]
    psi = psi / psi[q, range(n_modes)]

    files = {1: "Exp_form1_Jacon_interior-point.mat", 2: "Exp_form2_Jacon_interior-point.mat",
             3: "Exp_form3_Jacon_interior-point.mat"}
    Rs = {f: src.mat(f"{FS}/Results/{fn}") for f, fn in files.items()}
    for R in Rs.values():
        sm, em = R["structModel"], R["expModes"]
        assert np.array_equal(dense(sm.K0), sum(Kj)) and np.array_equal(dense(sm.M0), M)
        assert all(np.array_equal(dense(sm.K_j[j]), Kj[j]) for j in range(4))
        assert np.array_equal(np.ravel(em.lambdaExp), lam_exp) and np.array_equal(em.psiExp, psi)
        assert np.all(np.ravel(em.lambdaWeights) == 1) and np.all(np.ravel(em.psiWeights) == 1)

    labels = [f"floor{j}" for j in range(1, 5)]
    channels = [(f"floor{j + 1}", j) for j in meas]
    note = "SMU FourStoryStructureExperiment.m: storeys 10 lbf/in, floors 12.060 lb / 386.088 in/s²; lbf, in, s"
    write_model(out, "smu-four-storey", labels, Kj, names, ["matrix"] * 4, M, lo, hi, channels, note)

    std = np.ones_like(psi)
    std[q, range(n_modes)] = 0.0
    write_json(os.path.join(out, "data.json"), modal_set(
        "smu-four-storey", "2017-01-30T10:58:39Z", [c for c, _ in channels], f_exp,
        0.5 * np.ones(n_modes), psi, std,
        source=f"SMU {FS}/FourStoryStructure.mat @ {src.commit[:12]}: modes 1-2 at floors 1-3 "
               "(rows 1-3 of test_mode, divided by the entry of largest magnitude). No uncertainty "
               "is published: frequency_cov and shape_std are what the objective's unit weights "
               "imply (sigma_lambda = lambda, sigma_psi = 1); time = the MAT-file's creation time"))

    def form3_extra(x):
        theta = 1 + x[:4]
        prof, _ = mdr_profile(Kj, M, theta, meas, lam_exp, psi, [1.0, 1.0])
        return {"psi_unmeasured": [num(v) for v in x[4:]],
                "psi_unmeasured_rule": "x(5:6) = floor-4 entries of modes 1, 2 (ψ_i^U), bounds [−3, 3]",
                "objective_profiled_over_psi_unmeasured_computed": num(prof)}

    alg = "fmincon interior-point, analytical gradient, tolFun = tolX = 4.93e-32, 1000 starts (rng seed 2)"
    fits = [
        fit_entry("form1_mac", False, f"{FS}/Results/{files[1]}", alg, Rs[1], "alpha", 4, names, lo, hi, Kj, M, meas, psi),
        fit_entry("form2_eigenvector_difference", True, f"{FS}/Results/{files[2]}", alg, Rs[2], "alpha", 4, names, lo, hi, Kj, M, meas, psi),
        fit_entry("form3_modal_dynamic_residual", False, f"{FS}/Results/{files[3]}", alg, Rs[3], "alpha", 4, names, lo, hi, Kj, M, meas, psi, form3_extra),
    ]
    f0, mac0 = fit_summary(Kj, M, np.ones(4), meas, psi)
    write_json(os.path.join(out, "published.json"), {
        "case": "smu-four-storey",
        "source": {
            "repository": REPO_URL, "commit": src.commit, "license": "GPL-3.0",
            "files": [f"{FS}/FourStoryStructureExperiment.m", f"{FS}/FourStoryStructure.mat",
                      f"{FS}/StructuralDynamics/assemblyK.m", f"{FS}/StructuralDynamics/assemblyM.m",
                      *[f"{FS}/Results/{fn}" for fn in files.values()], f"{FS}/Results/PostProcess_Exp.m",
                      "SMU/StructModelUpdating.m", "SMU/OptmzObjJac.m", "SMU/ModelUpdatingObjective.m",
                      "SMU/ObjFuncMPDLsqnonlin.m", "SMU/ObjFuncMDRLsqnonlin.m", "SMU/MAC.m",
                      "SMU/MultiRunModelUpdating.m"],
        },
        "parameterization": "SMU: K(α) = K0 + Σ α_j K_j, K0 = Σ K_j (α = 0 nominal). Here: "
                            "K(θ) = Σ θ_l K_l, θ_l = 1 + α_l; bounds θ = 1 + α bounds.",
        "parameters": names,
        "alpha_lower": lo, "alpha_upper": hi,
        "theta_lower": [num(1 + a) for a in lo], "theta_upper": [num(1 + b) for b in hi],
        "objective": {
            "eigenproblem": "K(θ) ψ = λ M ψ; experimental mode i paired with the i-th lowest model mode (modeMatch = 2)",
            "lambda_exp": [num(x) for x in lam_exp],
            "reference_entry_q": q,
            "reference_entry_rule": "q_i = channel (0-based) of the largest |entry| of the measured shape, "
                                    "which is then 1 (FourStoryStructureExperiment.m)",
            "form1_mac": {
                "formula": "f(α) = Σ_i [w_λi (λ_i^exp − λ_i(α)) / λ_i^exp]² + [w_ψi (1 − √MAC_i) / √MAC_i]²",
                "lambda_weights": [1.0, 1.0], "psi_weights": [1.0, 1.0]},
            "form2_eigenvector_difference": {
                "formula": "f(α) = Σ_i [w_λi (λ_i^exp − λ_i(α)) / λ_i^exp]² + w_ψi² Σ_{k ≠ q_i} "
                           "(ψ_ki^exp − ψ_ki(α) / ψ_{q_i i}(α))²",
                "lambda_weights": [1.0, 1.0], "psi_weights_applied": [1.0, 1.0]},
            "form3_modal_dynamic_residual": {
                "formula": "f(α, ψ^U) = Σ_i w_i² ‖(K(α) − λ_i^exp M) [ψ_i^exp; ψ_i^U]‖², all 4 DOFs; "
                           "ψ_i^U (floor 4) are optimization variables too",
                "weights": [1.0, 1.0]},
        },
        "frequencies_hz_measured": [num(x) for x in f_exp],
        "frequencies_hz_measured_all": [num(x) for x in np.ravel(d["test_frequency"])],
        "nominal_theta": {"frequencies_hz_computed": f0, "mac_computed": mac0},
        "fits": fits,
    })


ES = "Examples/EighteenStoryStructure/Experiment"


def shear_18(src, out):
    d = src.mat(f"{ES}/ExpModalInfo_18DOF.mat")
    # EighteenStoryStructureExp.m
    k = np.array([1155, 1092, 1073, 1028, 1028, 990, 963, 938, 876, 840, 824, 788,
                  712, 660, 619, 562, 491, 363], dtype=float) * 10 ** 2  # kN/m
    weights = np.array([208] * 11 + [206] * 6 + [202], dtype=float)  # kN
    M = np.diag(weights / 9.8)  # t
    Kj = shear_kj(k)
    n_modes = 2
    meas = np.asarray(d["measDOFs"], dtype=int).ravel() - 1
    names = [f"storey{j:02d}" for j in range(1, 19)]
    lo, hi = [-0.3] * 18, [0.3] * 18
    lam_exp = np.asarray(d["lambdaExp"], dtype=float).ravel()[:n_modes]
    f_exp = np.asarray(d["freqExp"], dtype=float).ravel()[:n_modes]
    zeta = np.asarray(d["dampExp"], dtype=float).ravel()[:n_modes]
    psi = np.asarray(d["psiExp_m"], dtype=float)[:, :n_modes]
    q = [int(np.argmax(np.abs(psi[:, i]))) for i in range(n_modes)]
    psi = psi / psi[q, range(n_modes)]

    fn = "EighteenStoryStructureExp_form2_JACon_Interior-point.mat"
    R = src.mat(f"{ES}/Results/{fn}")
    sm, em = R["structModel"], R["expModes"]
    assert np.array_equal(dense(sm.K0), sum(Kj)) and np.array_equal(dense(sm.M0), M)
    assert all(np.array_equal(dense(sm.K_j[j]), Kj[j]) for j in range(18))
    assert np.array_equal(np.ravel(em.lambdaExp), lam_exp) and np.array_equal(em.psiExp[:, :n_modes], psi)
    assert np.all(np.ravel(em.lambdaWeights) == 100) and np.all(np.ravel(em.psiWeights) == 1)

    labels = [f"floor{j}" for j in range(1, 19)]
    channels = [(f"floor{j + 1}", j) for j in meas]
    note = "SMU EighteenStoryStructureExp.m: storey stiffness kN/m, floor mass t (weight kN / 9.8)"
    write_model(out, "smu-shear-18", labels, Kj, names, ["matrix"] * 18, M, lo, hi, channels, note)

    std = np.ones_like(psi)
    std[q, range(n_modes)] = 0.0
    write_json(os.path.join(out, "data.json"), modal_set(
        "smu-shear-18", "2020-11-10T17:17:54Z", [c for c, _ in channels], f_exp,
        0.5 / 100 * np.ones(n_modes), psi, std, damping=zeta,
        source=f"SMU {ES}/ExpModalInfo_18DOF.mat @ {src.commit[:12]}: modes 1-2 of the E-Defense "
               "18-storey frame at floors 3, 6, ..., 18. No uncertainty is published: frequency_cov "
               "and shape_std are what the objective's weights imply (w_lambda = 100: sigma_lambda = "
               "lambda / 100; w_psi = 1: sigma_psi = 1); time = the MAT-file's creation time"))

    fits = [fit_entry("form2_eigenvector_difference", True, f"{ES}/Results/{fn}",
                      "fmincon interior-point, analytical gradient (MATLAB default tolerances), 1000 starts (rng seed 2)",
                      R, "x", 18, names, lo, hi, Kj, M, meas, psi)]
    f0, mac0 = fit_summary(Kj, M, np.ones(18), meas, psi)
    write_json(os.path.join(out, "published.json"), {
        "case": "smu-shear-18",
        "source": {
            "repository": REPO_URL, "commit": src.commit, "license": "GPL-3.0",
            "files": [f"{ES}/EighteenStoryStructureExp.m", f"{ES}/ExpModalInfo_18DOF.mat",
                      f"{ES}/Results/{fn}", f"{ES}/Results/PostProcess18DOFExp.m", f"{ES}/Results/makeK.m",
                      "SMU/StructModelUpdating.m", "SMU/OptmzObjJac.m", "SMU/ModelUpdatingObjective.m",
                      "SMU/ObjFuncMPDLsqnonlin.m", "SMU/MultiRunModelUpdating.m"],
        },
        "parameterization": "SMU: K(α) = K0 + Σ α_j K_j, K0 = Σ K_j (α = 0 nominal). Here: "
                            "K(θ) = Σ θ_l K_l, θ_l = 1 + α_l; bounds θ = 1 + α bounds.",
        "parameters": names,
        "alpha_lower": lo, "alpha_upper": hi,
        "theta_lower": [num(round(1 + a, 12)) for a in lo], "theta_upper": [num(round(1 + b, 12)) for b in hi],
        "objective": {
            "eigenproblem": "K(θ) ψ = λ M ψ; experimental mode i paired with the i-th lowest model mode (modeMatch = 2)",
            "lambda_exp": [num(x) for x in lam_exp],
            "reference_entry_q": q,
            "reference_entry_rule": "q_i = channel (0-based) of the largest |entry| (floor 18 for both modes), "
                                    "which is 1 in the data file already",
            "form2_eigenvector_difference": {
                "formula": "f(α) = Σ_i [w_λi (λ_i^exp − λ_i(α)) / λ_i^exp]² + w_ψi² Σ_{k ≠ q_i} "
                           "(ψ_ki^exp − ψ_ki(α) / ψ_{q_i i}(α))²",
                "lambda_weights": [100.0, 100.0], "psi_weights_applied": [1.0, 1.0]},
        },
        "frequencies_hz_measured": [num(x) for x in f_exp],
        "frequencies_hz_measured_all": [num(x) for x in np.ravel(d["freqExp"])],
        "nominal_theta": {"frequencies_hz_computed": f0, "mac_computed": mac0},
        "fits": fits,
    })


def main():
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    src = Source(sys.argv[1])
    out = sys.argv[2] if len(sys.argv) > 2 else os.path.dirname(os.path.abspath(__file__))
    footbridge(src, os.path.join(out, "smu-footbridge"))
    four_storey(src, os.path.join(out, "smu-four-storey"))
    shear_18(src, os.path.join(out, "smu-shear-18"))
    print(f"SMU @ {src.commit}: wrote smu-footbridge, smu-four-storey, smu-shear-18 under {out}")


if __name__ == "__main__":
    main()
