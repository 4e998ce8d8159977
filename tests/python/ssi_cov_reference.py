#!/usr/bin/env python3
"""Independent numpy-only SSI-COV reference for the boltwatch test `oma` comparison.

Covariance-driven stochastic subspace identification (Peeters & De Roeck 1999) with
an automatic stabilisation diagram and jackknife standard deviations. It shares no code
with the Rust implementation; the Rust integration test runs it on the same record and
compares modes.

Usage:
    python ssi_cov_reference.py INPUT.csv --out RESULT.json [--block-rows 40]
        [--order-max 80] [--band lo,hi] [--refs 12] [--jackknife 10]

INPUT.csv: '#' lines and blank lines are ignored; the first remaining line is the header
`time_s,<ch1>,<ch2>,...`; every other line is one uniformly sampled row of floats.
The rate is 1 / median(diff(time)).

Choices (all fixed here, so the reference is reproducible):
* references: all channels if --refs 0 or --refs >= channels, otherwise the `refs`
  channels of largest variance (after mean removal), kept in their original order;
* covariances are unbiased: R_k = sum_t y_{t+k} y_ref,t^T / (N - k);
* a pole is physical when Im(lambda) > 0, 0 < zeta < 0.2 and lo <= f <= hi (default band
  0 .. 0.45 fs); it is stable when the next lower order (n - 2) has a physical pole q with
  |f/f_q - 1| < 1 %, |zeta/zeta_q - 1| < 30 % and complex MAC > 0.95;
* clusters: stable poles sorted by frequency; a pole more than 2 % above the running
  median of the current cluster starts a new one; a cluster is a mode when its poles come
  from at least 40 % of the orders that can hold stable poles (all orders but the lowest);
  `members` is its number of poles; the representative pole is the member nearest to the
  cluster's median frequency;
* jackknife: J contiguous blocks, each with its own covariances (within the block only);
  leave-one-out Hankel = mean of the other J-1 blocks' covariances; at the representative
  order, among the poles with MAC > 0.8 to the representative's shape (all poles with
  Im > 0 if none has), the one nearest to it in the s-plane, |lambda - lambda0| / |lambda0|
  ~ sqrt((df/f)^2 + dzeta^2): nearest in frequency, except that a spurious pole of very
  different damping (often negative) just beside the mode is not taken for it;
  sigma^2 = (J-1)/J sum (theta_j - mean)^2.
Exit status 2 with a message on stderr on bad input.
"""
import argparse
import json
import sys
import time

import numpy as np

MAX_DAMPING, DF, DXI, MAC_MIN, CLUSTER_DF, MIN_SHARE, JACK_MAC = 0.2, 0.01, 0.3, 0.95, 0.02, 0.4, 0.8


def fail(msg):
    sys.stderr.write(f"ssi_cov_reference: error: {msg}\n")
    sys.exit(2)


def read_csv(path):
    """Returns (time, Y[N x r], channel names). Finds the header line by hand, then lets
    numpy's C parser (np.loadtxt on the path: faster here than np.fromstring or parsing a
    list of lines) read the rest; '#' lines and blank lines are skipped by loadtxt too."""
    try:
        with open(path, "r", encoding="utf-8") as fh:
            for skip, line in enumerate(fh, start=1):
                if line.strip() and not line.lstrip().startswith("#"):
                    break
            else:
                fail("no header line")
    except (OSError, UnicodeDecodeError) as e:
        fail(f"cannot read {path}: {e}")
    names = [c.strip() for c in line.split(",")]
    if len(names) < 2 or names[0] != "time_s":
        fail(f"header must be 'time_s,<ch1>,...', got {line.strip()[:80]!r}")
    try:
        data = np.loadtxt(path, delimiter=",", comments="#", skiprows=skip, ndmin=2, dtype=np.float64)
    except (ValueError, UnicodeDecodeError) as e:  # bad field or ragged row (with its line)
        fail(f"cannot parse the data of {path}: {e}")
    if data.shape[0] < 2:
        fail("fewer than two data rows")
    if data.shape[1] != len(names):
        fail(f"rows have {data.shape[1]} fields but the header names {len(names)}")
    if not np.all(np.isfinite(data)):
        fail("non-finite value in the data")
    return data[:, 0], data[:, 1:], names[1:]


def lag_sums(y, yref, lags):
    """S_k = sum_t y_{t+k} y_ref,t^T, k = 0..lags, shape (lags+1, r, nref): one BLAS
    product per lag on strided views (no loop over samples)."""
    n = y.shape[0]
    return np.stack([y[k:].T @ yref[: n - k] for k in range(lags + 1)])


def covariances(y, yref, lags, n_blocks):
    """Unbiased covariances R_k = S_k / (N - k) of the whole record, and of each of
    `n_blocks` contiguous blocks (each from its own samples only). The whole record's sums
    are the blocks' sums plus the few products that straddle a block boundary (pairs
    t < e <= t + k), so the data are multiplied once, not twice."""
    n = y.shape[0]
    edges = np.linspace(0, n, n_blocks + 1).astype(int)
    k = np.arange(lags + 1)[:, None, None]
    sums = [lag_sums(y[a:b], yref[a:b], lags) for a, b in zip(edges[:-1], edges[1:])]
    blocks = np.stack([sj / (b - a - k) for sj, a, b in zip(sums, edges[:-1], edges[1:])])
    total = np.sum(sums, axis=0)
    for e in edges[1:-1]:
        for lag in range(1, lags + 1):
            total[lag] += y[e: e + lag].T @ yref[e - lag: e]
    return total / (n - k), blocks


def hankel_svd(cov, i):
    """Block Hankel H (i r x i nref), block (a, b) = R_{a+b+1}; returns U, s."""
    _, r, m = cov.shape
    idx = np.arange(i)[:, None] + np.arange(i)[None, :] + 1  # lag of block (a, b)
    h = cov[idx].transpose(0, 2, 1, 3).reshape(i * r, i * m)
    u, s, _ = np.linalg.svd(h, full_matrices=False)
    return u, s


def poles_at(u, s, n, r, fs):
    """Poles of order n with Im(lambda) > 0: (f [Hz], zeta, shapes r x p complex)."""
    o = u[:, :n] * np.sqrt(s[:n])               # observability O = U_n S_n^1/2
    c = o[:r]                                   # output matrix: first block row
    a = np.linalg.lstsq(o[:-r], o[r:], rcond=None)[0]  # shift invariance O_up A = O_down
    mu, psi = np.linalg.eig(a)
    keep = mu.imag > 0                          # one of each conjugate pair
    mu, psi = mu[keep], psi[:, keep]
    lam = np.log(mu) * fs                       # continuous-time poles
    f = np.abs(lam) / (2 * np.pi)
    zeta = -lam.real / np.abs(lam)
    return f, zeta, c @ psi


def mac(p, q):
    """Complex MAC between the columns of p (r x a) and q (r x b) -> (a x b)."""
    num = np.abs(p.conj().T @ q) ** 2
    den = np.outer(np.sum(np.abs(p) ** 2, 0), np.sum(np.abs(q) ** 2, 0))
    return num / np.maximum(den, np.finfo(float).tiny)


def select_modes(u, s, r, fs, orders, band):
    """Stabilisation diagram -> list of (f, zeta, order, members, shape)."""
    stable, prev = [], None
    for n in orders:
        f, z, phi = poles_at(u, s, n, r, fs)
        ok = (z > 0) & (z < MAX_DAMPING) & (f >= band[0]) & (f <= band[1])
        f, z, phi = f[ok], z[ok], phi[:, ok]
        if prev is not None and f.size and prev[0].size:
            fq, zq, phq = prev
            match = ((np.abs(f[:, None] / fq[None, :] - 1) < DF)
                     & (np.abs(z[:, None] / zq[None, :] - 1) < DXI)
                     & (mac(phi, phq) > MAC_MIN)).any(axis=1)
            stable += [(f[k], z[k], n, phi[:, k]) for k in np.flatnonzero(match)]
        prev = (f, z, phi)
    stable.sort(key=lambda p: p[0])
    clusters = []
    for p in stable:
        if clusters:
            fr = [q[0] for q in clusters[-1]]   # already sorted ascending
            med = 0.5 * (fr[(len(fr) - 1) // 2] + fr[len(fr) // 2])
            if p[0] <= med * (1 + CLUSTER_DF):
                clusters[-1].append(p)
                continue
        clusters.append([p])
    need = MIN_SHARE * max(len(orders) - 1, 1)
    modes = []
    for cl in clusters:
        if len({p[2] for p in cl}) < need:
            continue
        med = np.median([p[0] for p in cl])
        rep = min(cl, key=lambda p: abs(p[0] - med))
        modes.append((rep[0], rep[1], rep[2], len(cl), rep[3]))
    return modes


def s_plane_distance(f, z, f0, z0):
    """|lambda - lambda0| / |lambda0| for poles given by (f, zeta): about
    sqrt((df/f)^2 + dzeta^2), i.e. the frequency distance unless the damping differs."""
    lam = f * (-z + 1j * np.sqrt(1 - z * z))
    return np.abs(lam - f0 * (-z0 + 1j * np.sqrt(1 - z0 * z0))) / f0


def jackknife(blocks, i, r, fs, modes):
    """Leave-one-block-out standard deviations of (f, zeta) for each mode."""
    j_blocks = blocks.shape[0]
    total = blocks.sum(axis=0)
    est = np.empty((j_blocks, len(modes), 2))
    for j in range(j_blocks):
        u, s = hankel_svd((total - blocks[j]) / (j_blocks - 1), i)
        cache = {}
        for m, (f0, z0, order, _, shape0) in enumerate(modes):
            if order not in cache:
                cache[order] = poles_at(u, s, order, r, fs)
            f, z, phi = cache[order]
            cand = np.flatnonzero(mac(shape0[:, None], phi)[0] > JACK_MAC)
            if cand.size == 0:
                cand = np.arange(f.size)
            k = cand[np.argmin(s_plane_distance(f[cand], z[cand], f0, z0))]
            est[j, m] = f[k], z[k]
    var = (j_blocks - 1) / j_blocks * np.sum((est - est.mean(axis=0)) ** 2, axis=0)
    return np.sqrt(var)


def main(argv=None):
    t_start = time.perf_counter()
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("input")
    ap.add_argument("--out", required=True)
    ap.add_argument("--block-rows", type=int, default=40)
    ap.add_argument("--order-max", type=int, default=80)
    ap.add_argument("--band", default=None, help="lo,hi in Hz (default 0,0.45*fs)")
    ap.add_argument("--refs", type=int, default=12)
    ap.add_argument("--jackknife", type=int, default=10)
    a = ap.parse_args(argv)

    t0 = time.perf_counter()
    t, y, names = read_csv(a.input)
    seconds_parse = time.perf_counter() - t0

    n, r = y.shape
    dt = np.diff(t)
    step = float(np.median(dt))
    if not step > 0:
        fail("time column is not increasing")
    if np.max(np.abs(dt - step)) > 0.1 * step:
        fail("time column is not uniformly sampled (a step differs from the median by > 10 %)")
    fs = 1.0 / step
    if a.band is None:
        band = (0.0, 0.45 * fs)
    else:
        try:
            band = tuple(float(v) for v in a.band.split(","))
            assert len(band) == 2 and 0 <= band[0] < band[1]
        except (ValueError, AssertionError):
            fail(f"--band must be 'lo,hi' with 0 <= lo < hi, got {a.band!r}")
    i, jb = a.block_rows, a.jackknife
    if i < 2 or a.order_max < 2 or a.refs < 0 or jb < 2:
        fail("need --block-rows >= 2, --order-max >= 2, --refs >= 0, --jackknife >= 2")
    if n // jb < 4 * i:
        fail(f"{n} samples are too few for {jb} jackknife blocks of at least {4 * i} samples")

    t1 = time.perf_counter()
    # 1. Mean removal; references = the `refs` channels of largest variance (or all).
    y = y - y.mean(axis=0)
    if a.refs == 0 or a.refs >= r:
        refs = np.arange(r)
    else:
        refs = np.sort(np.argsort(-y.var(axis=0), kind="stable")[: a.refs])
    yref = np.ascontiguousarray(y[:, refs])
    # 2.-3. Covariances R_0..R_{2i-1} (record and jackknife blocks), block Hankel, SVD.
    cov, blocks = covariances(y, yref, 2 * i - 1, jb)
    u, s = hankel_svd(cov, i)
    # 4.-5. Orders 2, 4, ... (at most the rank the shift equation supports), poles, modes.
    n_max = min(a.order_max, (i - 1) * r, i * len(refs))
    orders = list(range(2, n_max + 1, 2))
    modes = select_modes(u, s, r, fs, orders, band)
    # 6. Jackknife over contiguous blocks.
    std = jackknife(blocks, i, r, fs, modes) if modes else np.zeros((0, 2))
    seconds_identify = time.perf_counter() - t1

    def num(v):
        return float(v) if np.isfinite(v) else None

    out = {
        "rate_hz": fs, "channels": r, "samples": n,
        "channel_names": names, "references": [names[k] for k in refs],
        "order_max_used": n_max, "band_hz": list(band),
        "modes": [{"frequency_hz": num(f), "frequency_std": num(sd[0]),
                   "damping_ratio": num(z), "damping_std": num(sd[1]),
                   "order": int(o), "members": int(m)}
                  for (f, z, o, m, _), sd in zip(modes, std)],
        "seconds_parse": seconds_parse, "seconds_identify": seconds_identify,
    }
    out["seconds_total"] = time.perf_counter() - t_start
    try:
        with open(a.out, "w") as fh:
            json.dump(out, fh, indent=1)
    except OSError as e:
        fail(f"cannot write {a.out}: {e}")


if __name__ == "__main__":
    main()
