"""The paper's site-by-site sweep (Qin 2020, Sec. 2, Steps 1-5): one site's equation at a time, a reference."""

from __future__ import annotations

import math

import numpy as np
import torch

from .._contract import AbstractLagrangian
from ._slices import _scale, _SliceSystem


def _sweep_slice(model: AbstractLagrangian, sys: _SliceSystem, psi, flat, i, vol, rtol, max_newton, f):
    """The paper's site-by-site sweep (Gauss-Seidel when the slice system is not triangular)."""
    st = sys.st
    m = sys.m
    nsp = len(sys.spatial)
    offs = np.array(st.offsets)
    sites = np.nonzero(sys.interior)[0]
    e0 = np.zeros(nsp + 1, dtype=np.int64)
    e0[0] = 1
    unk_scale = _scale(flat, i, torch.from_numpy(sites))
    total_it = 0
    worst = 0.0
    sweeps = 1 if sys.triangular else 100
    for _sweep in range(sweeps):
        change = 0.0
        for row, site in enumerate(sites):
            y = np.array([i, *np.unravel_index(site, sys.spatial)])
            # the K cells y - s_a, each with its K points y - s_a + s_b
            pts = y[None, None, :] - offs[:, None, :] + offs[None, :, :]
            for k in range(nsp):
                pts[..., k + 1] = sys.kinds[k].sites(pts[..., k + 1], sys.spatial[k])
            unknown = np.all(pts == (y + e0), axis=-1)  # (K, K)
            idx = tuple(torch.from_numpy(pts[..., d]) for d in range(nsp + 1))
            base = psi[idx].clone()  # (K, K, m)
            u = psi[tuple(int(v) for v in y + e0)].clone()
            mask = torch.from_numpy(unknown)
            for _ in range(max_newton):
                total_it += 1
                uu = u.clone().requires_grad_(True)
                with torch.enable_grad():
                    x = torch.where(mask[..., None], uu.expand_as(base), base)
                    (g,) = torch.autograd.grad(model(x).sum(), x, create_graph=True)
                    el = vol * g[torch.arange(st.size), torch.arange(st.size)].sum(0)  # sum_a d_a L(cell y - s_a)
                    jac = torch.stack([torch.autograd.grad(el[c], uu, retain_graph=True)[0] for c in range(m)])
                res = float(el.detach().abs().max())
                if not math.isfinite(res):
                    return total_it, res, None, ("residual is not finite", row * m, res)
                try:
                    step = torch.linalg.solve(jac, -el.detach())
                except RuntimeError:
                    return total_it, res, None, ("singular mixed Hessian", row * m, res)
                u = u + step
                if float(step.abs().max()) <= rtol * unk_scale:
                    break
            else:
                return total_it, res, None, (f"Newton did not converge in {max_newton} iterations", row * m, res)
            old = psi[tuple(int(v) for v in y + e0)]
            change = max(change, float((u - old).abs().max()))
            psi[tuple(int(v) for v in y + e0)] = u
            worst = max(worst, res)
        if sys.triangular or change <= 10 * rtol * unk_scale:
            break
    else:
        return total_it, worst, None, ("site-by-site sweeps did not converge", None, worst)
    return total_it, worst, None, None
