"""A plain SciPy Gauss-Newton mode-matching update: the reference `boltwatch update` is
timed against (issue 27).

Not boltwatch: numpy and scipy read the matrices `boltwatch export-matrices` wrote and a
modal set (boltwatch.modal_set.v1), and minimize the paper's objective (5) with the
residual (6): per measured mode, the eigenvalue error and the shape error after the scale
factor (7), whitened by the set's uncertainties (28) (eigenvalue std 2 V^f lambda, shape
entry std RMS(psi) * NSD). Each iteration:

- K(theta) = K0 + sum_l theta_l K_l, and the lowest max(2m, m + 10) modes by the dense
  generalized symmetric eigensolver (scipy.linalg.eigh, LAPACK);
- every measured mode paired with the candidate of largest MAC at the channels;
- exact sensitivities: d lambda / d theta_l = phi^T K_l phi, and d phi / d theta_l by
  Nelson's method (a dense solve of (K - lambda M) v = -(K_l - d lambda M) phi with the
  largest component of phi pinned, then v - (phi^T M v) phi);
- the Gauss-Newton step, the least-squares solution of J d = -r (numpy.linalg.lstsq).

It stops after --iterations steps or when every |d_l / theta_l| is below --tol, and
prints one JSON object: theta, epsilon, iterations.

Usage: python gauss_newton_reference.py MATRICES_DIR SET.json [--theta0 1] [--iterations 50]
       [--tol 1e-5]
"""

import argparse
import json
from pathlib import Path

import numpy as np
import scipy.io
import scipy.linalg


def dense(path):
    return np.asarray(scipy.io.mmread(path).toarray(), dtype=float)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("matrices")
    ap.add_argument("data")
    ap.add_argument("--theta0", type=float, default=1.0)
    ap.add_argument("--iterations", type=int, default=50)
    ap.add_argument("--tol", type=float, default=1e-5)
    args = ap.parse_args()

    d = Path(args.matrices)
    meta = json.loads((d / "model.json").read_text())
    k0 = dense(d / "K0.mtx")
    k_l = [dense(d / p["file"]) for p in meta["parameters"]]
    m = dense(d / "M.mtx")
    n = k0.shape[0]
    # Each model channel reads a combination of DOFs: a row of the reading matrix D.
    names = [c["name"] for c in meta["channels"]]
    read = np.zeros((len(names), n))
    for c, ch in enumerate(meta["channels"]):
        for i, w in ch["dofs"]:
            read[c, i] += w

    data = json.loads(Path(args.data).read_text())
    rows = [names.index(c) for c in data["channels"]]
    modes = []
    for mode in data["modes"]:
        lam = (2 * np.pi * mode["frequency_hz"]) ** 2
        shape = mode.get("shape")
        entry = {"lam": lam, "sigma_lam": 2 * mode["frequency_cov"] * lam}
        if shape is not None:
            kept = [(r, v) for r, v in zip(rows, shape) if v is not None]
            psi = np.array([v for _, v in kept])
            entry["d"] = read[[r for r, _ in kept]]
            entry["psi"] = psi
            entry["sigma"] = np.sqrt(np.mean(psi**2)) * mode["shape_nsd"]
        modes.append(entry)
    n_cand = min(max(2 * len(modes), len(modes) + 10), n)

    theta = np.full(len(k_l), args.theta0)
    iterations, converged = 0, False
    while True:
        k = k0 + sum(t * kl for t, kl in zip(theta, k_l))
        lam, phi = scipy.linalg.eigh(k, m, subset_by_index=[0, n_cand - 1])
        r, jac = [], []
        for mode in modes:
            if "psi" in mode:
                dphi_all = mode["d"] @ phi
                num = (mode["psi"] @ dphi_all) ** 2
                den = (mode["psi"] @ mode["psi"]) * np.sum(dphi_all**2, axis=0)
                j = int(np.argmax(num / den))
            else:
                j = int(np.argmin(np.abs(lam - mode["lam"])))
            p = phi[:, j]
            dlam = np.array([p @ kl @ p for kl in k_l])
            # Nelson: pin the largest component, solve, restore the mass normalization.
            a = k - lam[j] * m
            pin = int(np.argmax(np.abs(p)))
            a[pin, :] = 0.0
            a[:, pin] = 0.0
            a[pin, pin] = 1.0
            f = np.column_stack([-(kl - dl * m) @ p for kl, dl in zip(k_l, dlam)])
            f[pin, :] = 0.0
            v = np.linalg.solve(a, f)
            v = v - np.outer(p, p @ m @ v)
            r.append((mode["lam"] - lam[j]) / mode["sigma_lam"])
            jac.append(-dlam / mode["sigma_lam"])
            if "psi" in mode:
                dp = mode["d"] @ p
                ddp = mode["d"] @ v
                c = (mode["psi"] @ dp) / (dp @ dp)
                dc = ((mode["psi"] - 2 * c * dp) @ ddp) / (dp @ dp)
                r.extend((mode["psi"] - c * dp) / mode["sigma"])
                jac.extend(-(c * ddp + np.outer(dp, dc)) / mode["sigma"])
        r, jac = np.array(r), np.array(jac)
        if converged or iterations == args.iterations:
            break
        step = np.linalg.lstsq(jac, -r, rcond=None)[0]
        theta = theta + step
        iterations += 1
        converged = bool(np.all(np.abs(step / theta) < args.tol))
    print(
        json.dumps(
            {
                "theta": theta.tolist(),
                "epsilon": float(r @ r),
                "iterations": iterations,
                "converged": converged,
            }
        )
    )


if __name__ == "__main__":
    main()
