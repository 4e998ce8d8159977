"""An independent program builds a parametric model and its measured data (issue 24).

Not boltwatch: numpy and scipy assemble a planar Euler-Bernoulli cantilever (100 elements,
200 DOF: transverse displacement and rotation of nodes 1..100, node 0 clamped) whose
bending stiffness EI is scaled by five parameters, one per segment of 20 elements:
K(theta) = sum_l theta_l K_l (no K0). The mass is lumped on the translations (the
rotations carry none, as an FE program's lumped masses leave them), so the script's own
eigen solution condenses the rotations out statically.

It writes, under OUT:
  model/   boltwatch.matrices.v1: model.json, K_seg<l>.mtx (scipy.io.mmwrite), M.mtx,
           dofs.txt
  sets/    <k>.json for k < DRAWS: boltwatch.modal_set.v1 at theta_true, the frequencies
           with 1 % CoV noise, each shape scaled to unit largest entry with independent
           noise of a per-entry std (shape_std) that differs from channel to channel
  truth.json  theta_true and the exact frequencies at theta_true and at theta = 1

Usage: python independent_model.py OUT DRAWS
"""

import json
import sys
from pathlib import Path

import numpy as np
import scipy.io
import scipy.linalg
import scipy.sparse

N_EL = 100
LENGTH = 4.0
EI = 210e9 * 1.0e-6  # N m^2
RHO_A = 7850.0 * 1.0e-3  # kg/m
N_PAR = 5
THETA_TRUE = [0.8, 1.1, 0.9, 1.2, 0.7]
N_MODES = 8
FREQ_COV = 0.01
CHANNEL_NODES = list(range(5, N_EL + 1, 5))  # 20 channels


def element_stiffness(ei, le):
    """Euler-Bernoulli beam element, DOFs (v1, r1, v2, r2)."""
    c = ei / le**3
    return c * np.array(
        [
            [12.0, 6.0 * le, -12.0, 6.0 * le],
            [6.0 * le, 4.0 * le**2, -6.0 * le, 2.0 * le**2],
            [-12.0, -6.0 * le, 12.0, -6.0 * le],
            [6.0 * le, 2.0 * le**2, -6.0 * le, 4.0 * le**2],
        ]
    )


def dof(node, which):
    """Index of a free DOF: node 1..N_EL, which 0 (v) or 1 (r); None for the clamp."""
    if node == 0:
        return None
    return 2 * (node - 1) + which


def assemble():
    n = 2 * N_EL
    le = LENGTH / N_EL
    ke = element_stiffness(EI, le)
    k_par = [np.zeros((n, n)) for _ in range(N_PAR)]
    per = N_EL // N_PAR
    for e in range(N_EL):
        idx = [dof(e, 0), dof(e, 1), dof(e + 1, 0), dof(e + 1, 1)]
        kl = k_par[e // per]
        for a in range(4):
            for b in range(4):
                if idx[a] is not None and idx[b] is not None:
                    kl[idx[a], idx[b]] += ke[a, b]
    m = np.zeros((n, n))
    for node in range(1, N_EL + 1):
        share = 0.5 if node == N_EL else 1.0
        m[dof(node, 0), dof(node, 0)] = share * RHO_A * le
    return k_par, m


def modes(k_par, m, theta, n_modes):
    """Lowest modes with the massless rotations condensed out; shapes on every DOF,
    mass-normalized."""
    k = sum(t * kl for t, kl in zip(theta, k_par))
    n = k.shape[0]
    v = [i for i in range(n) if m[i, i] > 0.0]
    r = [i for i in range(n) if m[i, i] == 0.0]
    krr = k[np.ix_(r, r)]
    krv = k[np.ix_(r, v)]
    x = scipy.linalg.solve(krr, krv, assume_a="pos")
    khat = k[np.ix_(v, v)] - krv.T @ x
    khat = 0.5 * (khat + khat.T)
    # The inverse pencil M z = mu K z, mu = 1/lambda: LAPACK's error is about eps times
    # the largest eigenvalue, which this way is the wanted one (eigh(K, M) would give the
    # lowest lambda only to eps * lambda_max / lambda_1, ~2e-8 here).
    mvv = m[np.ix_(v, v)]
    nv = len(v)
    mu, z = scipy.linalg.eigh(mvv, khat, subset_by_index=[nv - n_modes, nv - 1])
    lam = 1.0 / mu[::-1]
    phiv = z[:, ::-1]
    phiv = phiv / np.sqrt(np.einsum("iq,ij,jq->q", phiv, mvv, phiv))
    phi = np.zeros((n, n_modes))
    phi[v, :] = phiv
    phi[r, :] = -x @ phiv
    return lam, phi


def main():
    out = Path(sys.argv[1])
    draws = int(sys.argv[2])
    k_par, m = assemble()
    n = m.shape[0]
    model = out / "model"
    model.mkdir(parents=True, exist_ok=True)
    for l, kl in enumerate(k_par):
        scipy.io.mmwrite(
            str(model / f"K_seg{l + 1}.mtx"),
            scipy.sparse.coo_matrix(kl),
            symmetry="symmetric",
            precision=17,
        )
    scipy.io.mmwrite(
        str(model / "M.mtx"), scipy.sparse.coo_matrix(m), symmetry="symmetric", precision=17
    )
    labels = [f"n{node:03d}.{w}" for node in range(1, N_EL + 1) for w in ("v", "r")]
    (model / "dofs.txt").write_text("\n".join(labels) + "\n")
    channels = [f"v{node:03d}" for node in CHANNEL_NODES]
    (model / "model.json").write_text(
        json.dumps(
            {
                "schema": "boltwatch.matrices.v1",
                "structure": "scipy-cantilever",
                "n_dof": n,
                "k0": None,
                "mass": "M.mtx",
                "parameters": [
                    {"name": f"EI{l + 1}", "file": f"K_seg{l + 1}.mtx", "kind": "modulus"}
                    for l in range(N_PAR)
                ],
                "channels": [
                    {"name": c, "dofs": [[dof(node, 0), 1.0]]}
                    for c, node in zip(channels, CHANNEL_NODES)
                ],
                "locations": [{"name": "tip", "dofs": [dof(N_EL, 0)]}],
            },
            indent=1,
        )
    )

    lam, phi = modes(k_par, m, THETA_TRUE, N_MODES)
    lam1, _ = modes(k_par, m, [1.0] * N_PAR, N_MODES)
    freq = np.sqrt(lam) / (2.0 * np.pi)
    (out / "truth.json").write_text(
        json.dumps(
            {
                "theta": THETA_TRUE,
                "frequencies_hz": freq.tolist(),
                "frequencies_hz_nominal": (np.sqrt(lam1) / (2.0 * np.pi)).tolist(),
            }
        )
    )
    rows = [dof(node, 0) for node in CHANNEL_NODES]
    shapes = phi[rows, :]
    shapes = shapes / np.abs(shapes).max(axis=0)
    # Per-entry std, fixed per channel and mode: 1 % to 5 % of the largest entry.
    spread = np.random.default_rng(7).uniform(0.01, 0.05, size=shapes.shape)
    sets = out / "sets"
    sets.mkdir(exist_ok=True)
    for k in range(draws):
        rng = np.random.default_rng(1000 + k)
        f_hat = freq * (1.0 + FREQ_COV * rng.standard_normal(N_MODES))
        psi_hat = shapes + spread * rng.standard_normal(shapes.shape)
        body = {
            "schema": "boltwatch.modal_set.v1",
            "structure": "scipy-cantilever",
            "time": "2026-01-01T00:00:00Z",
            "channels": channels,
            "modes": [
                {
                    "frequency_hz": float(f_hat[q]),
                    "frequency_cov": FREQ_COV,
                    "shape": psi_hat[:, q].tolist(),
                    "shape_std": spread[:, q].tolist(),
                }
                for q in range(N_MODES)
            ],
            "source": f"independent_model.py draw {k}",
        }
        (sets / f"{k}.json").write_text(json.dumps(body))


if __name__ == "__main__":
    main()
