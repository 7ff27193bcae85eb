"""
Orthogonal Matching Pursuit (Pati et al., 1993) in torch, batched over targets, without the feature Gram matrix. The
path is nested: one run gives the solution for every sparsity ``tau <= max_atoms``. It matches scikit-learn's
``OrthogonalMatchingPursuit(precompute=False)``, early stops and ties included: docs/probe.md#omp.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch as th
from stable_baselines3.common.utils import get_device

from sb3_collapse.common.progress import progress_bar


@dataclass
class OMPPath:
    """
    The OMP solutions for every sparsity ``1..max_atoms`` of ``m`` targets.

    :param indices: ``(m, max_atoms)`` long: the selected features of each target, in the order of
        selection; ``-1`` after the target's early stop
    :param coef_path: ``(m, max_atoms, max_atoms)`` float64: ``coef_path[j, :, t - 1]`` are the coefficients,
        on ``indices[j]``, of the solution with ``t`` atoms (zero beyond its ``t`` atoms); after an early stop
        at ``n_active[j]`` atoms, the solutions for larger ``t`` repeat the last one (as scikit-learn returns)
    :param n_active: ``(m,)`` long: atoms selected before the early stop (``max_atoms`` if none)
    """

    indices: th.Tensor
    coef_path: th.Tensor
    n_active: th.Tensor

    @property
    def max_atoms(self) -> int:
        """Largest sparsity of the path."""
        return int(self.indices.shape[1])

    def coefficients(self, n_atoms: int | th.Tensor, n_features: int) -> th.Tensor:
        """
        :param n_atoms: the sparsity ``tau`` (``1..max_atoms``), one for all targets or one per target ``(m,)``
        :param n_features: ``d``, the number of columns of ``X``
        :return: ``(m, d)`` float64 dense coefficients of those solutions, zero outside the selected atoms
        """
        m = self.indices.shape[0]
        taus = th.as_tensor(n_atoms, device=self.indices.device).expand(m).long()
        if (taus < 1).any() or (taus > self.max_atoms).any():
            raise ValueError(f"n_atoms must be in 1..{self.max_atoms}, got {taus.tolist()}.")
        rows = th.arange(m, device=self.indices.device)
        coef = self.coef_path[rows, :, taus - 1]  # (m, max_atoms)
        dense = th.zeros(m, n_features, dtype=th.float64, device=self.indices.device)
        valid = self.indices >= 0
        dense[rows[:, None].expand_as(self.indices)[valid], self.indices[valid]] = coef[valid]
        return dense


def omp_path(
    X: th.Tensor,
    Y: th.Tensor,
    max_atoms: int,
    x_offset: th.Tensor | None = None,
    progress: bool = False,
    desc: str = "OMP",
) -> OMPPath:
    """
    OMP of every column of ``Y`` on the columns of ``X``, up to ``max_atoms`` atoms. The correlations ``X^T R`` are
    computed in ``X``'s dtype on ``X``'s device (float64 reproduces scikit-learn); the least squares in float64.

    :param X: ``(n, d)`` features (float32 or float64), not modified
    :param Y: ``(n,)`` or ``(n, m)`` targets
    :param max_atoms: largest sparsity ``tau``, in ``1..d``
    :param x_offset: ``(d,)``: fit on ``X - x_offset`` without building it (the column means, to fit an
        intercept on centred data; ``Y`` must then be centred by the caller); ``None`` for ``X`` as is
    :param progress: show a progress bar over the iterations
    :param desc: label of the progress bar
    :return: the path of every target
    """
    if X.ndim != 2 or not X.is_floating_point():
        raise ValueError(f"X must be a 2-d float tensor, got shape {tuple(X.shape)} and dtype {X.dtype}.")
    n, d = X.shape
    Y = Y[:, None] if Y.ndim == 1 else Y
    if Y.ndim != 2 or Y.shape[0] != n:
        raise ValueError(f"Y must have {n} rows like X, got shape {tuple(Y.shape)}.")
    if not 1 <= max_atoms <= d:
        raise ValueError(f"max_atoms must be in 1..{d} (the number of features), got {max_atoms}.")
    device, m = X.device, Y.shape[1]
    f64 = {"dtype": th.float64, "device": device}
    eps = th.finfo(X.dtype).eps
    Y64 = Y.to(**f64)
    offset = None if x_offset is None else x_offset.to(device=device, dtype=X.dtype)

    indices = th.full((m, max_atoms), -1, dtype=th.long, device=device)
    chol = th.zeros(m, max_atoms, max_atoms, **f64)  # lower Cholesky factor of X_S^T X_S
    atoms = th.zeros(m, max_atoms, n, **f64)  # selected (centred) columns, one row each
    alpha = th.zeros(m, max_atoms, **f64)  # x_a^T y of the selected atoms
    coef_path = th.zeros(m, max_atoms, max_atoms, **f64)
    n_active = th.full((m,), max_atoms, dtype=th.long, device=device)
    residual = Y64.clone()  # (n, m)
    running = th.arange(m, device=device)  # targets still selecting atoms
    initial_correlations: th.Tensor | None = None  # X^T y, (d, m): set at k = 0, where every target runs

    for k in progress_bar(range(max_atoms), desc, "atom", progress, leave=False):
        if running.numel() == 0:
            break
        sel = _selector(running, m)
        R = residual[:, sel].to(X.dtype)
        correlations = X.T @ R  # (d, r): the one large product of the iteration
        if offset is not None:
            correlations -= offset[:, None] * R.sum(0)[None, :]
        if initial_correlations is None:  # k = 0: residual = y and all m targets run, so columns = target ids
            initial_correlations = correlations
        new = correlations.abs().argmax(0)  # (r,): the first maximum, so ties go to the lowest feature index

        x_new = X[:, new].T.to(th.float64)  # (r, n)
        if offset is not None:
            x_new -= offset[new, None].to(th.float64)
        squared_norm = (x_new * x_new).sum(1)
        if k > 0:
            cross = th.bmm(atoms[sel, :k], x_new.unsqueeze(2))  # (r, k, 1): X_S^T x_new
            v = th.linalg.solve_triangular(chol[sel, :k, :k], cross, upper=False).squeeze(2)
            # The new row of L L^T = X_S^T X_S: pivot = ||x_new||^2 - ||v||^2, the squared distance of x_new from
            # the span of the selected atoms.
            pivot = squared_norm - (v * v).sum(1)
            already = (indices[sel, :k] == new[:, None]).any(1)
        else:
            v, pivot = None, squared_norm
            already = th.zeros_like(new, dtype=th.bool)
        # scikit-learn's early stops (_cholesky_omp), in its order: an atom selected again (the residual is orthogonal
        # to the selected atoms, so the largest |x_i^T r| falls on one only when every correlation is rounding);
        # x_a^T y too small ((x_a^T y)^2 < eps, its alpha[lam] ** 2 < min_float); x_new in the selected atoms' span
        # (pivot <= eps: L would not stay positive definite). eps: the machine epsilon of X's dtype.
        negligible = initial_correlations[new, running].to(th.float64) ** 2 < eps
        stop = already | negligible | (pivot <= eps)
        if stop.any():  # a stopped target keeps its k atoms: n_active = k, its path filled after the loop
            n_active[running[stop]] = k
            keep = ~stop
            running, new, x_new, pivot = running[keep], new[keep], x_new[keep], pivot[keep]
            v = None if v is None else v[keep]
            if running.numel() == 0:
                break
            sel = _selector(running, m)
        if v is not None:
            chol[sel, k, :k] = v
        chol[sel, k, k] = pivot.sqrt()
        atoms[sel, k] = x_new
        indices[sel, k] = new
        alpha[sel, k] = (x_new * Y64[:, sel].T).sum(1)  # x_a^T y, not the residual: L L^T w = X_S^T y
        gamma = th.cholesky_solve(alpha[sel, : k + 1, None], chol[sel, : k + 1, : k + 1])  # (r, k+1, 1)
        coef_path[sel, : k + 1, k] = gamma.squeeze(2)
        fitted = th.bmm(gamma.transpose(1, 2), atoms[sel, : k + 1]).squeeze(1)  # (r, n)
        residual[:, sel] = Y64[:, sel] - fitted.T

    for j in th.nonzero(n_active < max_atoms).flatten().tolist():  # early stops: keep the last solution
        last = int(n_active[j])
        if last > 0:
            coef_path[j, :, last:] = coef_path[j, :, last - 1 : last]
    return OMPPath(indices=indices, coef_path=coef_path, n_active=n_active)


def _selector(running: th.Tensor, m: int) -> th.Tensor | slice:
    """Index of the running targets: a slice (views, no copies) while all ``m`` run."""
    return slice(None) if running.numel() == m else running


def path_predictions(X: th.Tensor, path: OMPPath, x_offset: th.Tensor | None = None) -> th.Tensor:
    """
    Predictions of every solution of a path: ``pred[i, j, t - 1] = (X[i] - x_offset) @ w_{j,t}``, reading only the
    selected columns of ``X``.

    :param X: ``(n, d)`` features, as given to :func:`omp_path`
    :param path: the path
    :param x_offset: the ``x_offset`` given to :func:`omp_path`
    :return: ``(n, m, max_atoms)`` float64 (add the targets' offsets for an intercept)
    """
    m, max_atoms = path.indices.shape
    idx = path.indices.clamp(min=0).to(X.device)
    selected = X[:, idx.reshape(-1)].reshape(X.shape[0], m, max_atoms).to(th.float64)
    if x_offset is not None:
        selected -= x_offset.to(device=X.device, dtype=th.float64)[idx]
    return th.einsum("nmk,mkt->nmt", selected, path.coef_path.to(X.device))


class OrthogonalMatchingPursuit:
    """
    scikit-learn's ``OrthogonalMatchingPursuit(precompute=False)`` on :func:`omp_path`, all targets fitted together
    (same atoms, same coefficients up to rounding).

    :param n_nonzero_coefs: the sparsity ``tau``: atoms per target
    :param fit_intercept: fit on centred ``X`` and ``y`` and set ``intercept_`` (``X`` is not copied)
    :param dtype: dtype of ``X`` in the large products (``None``: ``X``'s own if float32/float64)
    :param device: ``"auto"`` (CUDA when available), ``"cpu"``, ``"cuda"``, ...
    :param progress: show a progress bar over the iterations
    """

    def __init__(
        self,
        n_nonzero_coefs: int,
        fit_intercept: bool = True,
        dtype: th.dtype | None = None,
        device: th.device | str = "auto",
        progress: bool = False,
    ) -> None:
        self.n_nonzero_coefs = n_nonzero_coefs
        self.fit_intercept = fit_intercept
        self.dtype = dtype
        self.device = device
        self.progress = progress

    def _features(self, X: np.ndarray | th.Tensor) -> th.Tensor:
        X = th.as_tensor(X)
        dtype = self.dtype or (X.dtype if X.dtype in (th.float32, th.float64) else th.float32)
        return X.to(device=get_device(self.device), dtype=dtype)

    def fit(self, X: np.ndarray | th.Tensor, y: np.ndarray | th.Tensor) -> OrthogonalMatchingPursuit:
        """
        :param X: ``(n, d)`` features
        :param y: ``(n,)`` or ``(n, m)`` targets
        :return: self, with ``coef_`` (``(d,)`` or ``(m, d)``), ``intercept_`` (float or ``(m,)``),
            ``n_iter_`` (atoms selected per target) and ``path_`` (:class:`OMPPath`), as float64 numpy arrays
        """
        features = self._features(X)
        targets = th.as_tensor(y).to(device=features.device, dtype=th.float64)
        single = targets.ndim == 1
        targets = targets.reshape(len(targets), -1)
        x_offset = y_offset = None
        if self.fit_intercept:
            x_offset = features.mean(0, dtype=th.float64).to(features.dtype)
            y_offset = targets.mean(0)
            targets = targets - y_offset
        path = omp_path(features, targets, self.n_nonzero_coefs, x_offset=x_offset, progress=self.progress)
        coef = path.coefficients(self.n_nonzero_coefs, features.shape[1])
        intercept = th.zeros(coef.shape[0], dtype=th.float64, device=coef.device)
        if self.fit_intercept:
            intercept = y_offset - coef @ x_offset.to(th.float64)
        self.path_ = path
        self.n_iter_ = path.n_active.cpu().numpy()
        self.coef_ = coef.cpu().numpy()
        self.intercept_ = intercept.cpu().numpy()
        if single:
            self.coef_, self.intercept_, self.n_iter_ = self.coef_[0], float(self.intercept_[0]), int(self.n_iter_[0])
        return self

    def predict(self, X: np.ndarray | th.Tensor) -> np.ndarray:
        """
        :param X: ``(n, d)`` features
        :return: ``X @ coef_.T + intercept_``: ``(n,)`` or ``(n, m)``, float64
        """
        features = th.as_tensor(X).to(th.float64).cpu().numpy()
        return features @ self.coef_.T + self.intercept_
