import warnings

import numpy as np
import pytest
import torch as th
from sklearn.linear_model import OrthogonalMatchingPursuit as SklearnOMP
from sklearn.linear_model import orthogonal_mp

from sb3_collapse.probe.omp import OrthogonalMatchingPursuit, omp_path, path_predictions


def well_conditioned(n=150, d=400, m=4, seed=0):
    rng = np.random.default_rng(seed)
    X = rng.standard_normal((n, d))
    Y = X[:, :30] @ rng.standard_normal((30, m)) + 0.3 * rng.standard_normal((n, m)) + 2.0
    return X, Y


def sklearn_order(X, y, tau):
    """Atoms in the order scikit-learn selects them (the new non-zero of each step of its path)."""
    path = orthogonal_mp(X, y, n_nonzero_coefs=tau, precompute=False, return_path=True).reshape(X.shape[1], -1)
    order = []
    for step in range(path.shape[1]):
        order += [int(i) for i in np.flatnonzero(path[:, step]) if i not in order]
    return order


@pytest.mark.parametrize("fit_intercept", [False, True])
def test_same_atoms_and_coefficients_as_sklearn(fit_intercept):
    X, Y = well_conditioned()
    for tau in (1, 4, 12, 25):
        ours = OrthogonalMatchingPursuit(tau, fit_intercept=fit_intercept, device="cpu").fit(X, Y)
        ref = SklearnOMP(n_nonzero_coefs=tau, fit_intercept=fit_intercept, precompute=False).fit(X, Y)
        np.testing.assert_allclose(ours.coef_, ref.coef_, rtol=1e-5, atol=1e-12)
        np.testing.assert_allclose(ours.intercept_, ref.intercept_, rtol=1e-5, atol=1e-12)
        np.testing.assert_allclose(ours.predict(X), ref.predict(X), rtol=1e-5)
        assert (ours.n_iter_ == tau).all()
    # Selection order along the path, target by target (sklearn centres X and y itself when fitting an intercept).
    Xc, Yc = (X - X.mean(0), Y - Y.mean(0)) if fit_intercept else (X, Y)
    path = omp_path(th.as_tensor(Xc), th.as_tensor(Yc), 25)
    for j in range(Y.shape[1]):
        assert path.indices[j].tolist() == sklearn_order(Xc, Yc[:, j], 25)


def test_float32_products_select_the_same_atoms():
    X, Y = well_conditioned(seed=1)
    ours = omp_path(th.as_tensor(X, dtype=th.float32), th.as_tensor(Y - Y.mean(0)), 20)
    ref = omp_path(th.as_tensor(X), th.as_tensor(Y - Y.mean(0)), 20)
    assert th.equal(ours.indices, ref.indices)
    np.testing.assert_allclose(ours.coef_path.numpy(), ref.coef_path.numpy(), rtol=1e-3, atol=1e-6)


def test_path_is_nested_and_predictions_match_coefficients():
    X, Y = well_conditioned(m=3)
    Xt, Yt = th.as_tensor(X), th.as_tensor(Y)
    path = omp_path(Xt, Yt, 10)
    preds = path_predictions(Xt, path)  # (n, m, 10)
    for tau in (1, 5, 10):
        coef = path.coefficients(tau, X.shape[1])
        assert ((coef != 0).sum(1) == tau).all()
        th.testing.assert_close(preds[:, :, tau - 1], Xt @ coef.T)
        fit = SklearnOMP(n_nonzero_coefs=tau, fit_intercept=False, precompute=False).fit(X, Y)
        np.testing.assert_allclose(coef.numpy(), fit.coef_, rtol=1e-5, atol=1e-12)


def test_early_stops_match_sklearn():
    rng = np.random.default_rng(2)
    base = rng.standard_normal((40, 3))
    X = np.hstack([base, 2 * base])  # each atom has a linearly dependent twin
    Y = np.stack([rng.standard_normal(40), np.zeros(40)], axis=1)  # a random target and a zero one
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # sklearn warns that it stopped early
        ref = SklearnOMP(n_nonzero_coefs=5, fit_intercept=False, precompute=False).fit(X, Y)
    ours = OrthogonalMatchingPursuit(5, fit_intercept=False, device="cpu").fit(X, Y)
    assert ours.n_iter_.tolist() == [3, 0] == list(ref.n_iter_)
    np.testing.assert_allclose(ours.coef_, ref.coef_, rtol=1e-5, atol=1e-12)
    # After the stop, larger sparsities keep the last solution.
    assert th.equal(ours.path_.coef_path[0, :, 2], ours.path_.coef_path[0, :, 4])


def test_very_wide_layers_without_a_gram_matrix():
    """63,504 features (cnn0 at 84x84): a d x d Gram matrix would take 16 GB in float32."""
    rng = np.random.default_rng(3)
    X = th.as_tensor(rng.standard_normal((64, 63_504), dtype=np.float32))
    Y = X[:, [10, 40_000]] @ th.tensor([[1.0, 0.5], [-2.0, 1.0]]) + 0.01 * th.randn(64, 2)
    path = omp_path(X, Y, 4)
    assert path.indices[:, :2].sort(1).values.tolist() == [[10, 40_000], [10, 40_000]]


def test_bad_arguments_are_refused():
    X = th.zeros(5, 3)
    with pytest.raises(ValueError, match="max_atoms"):
        omp_path(X, th.zeros(5), 4)
    with pytest.raises(ValueError, match="rows"):
        omp_path(X, th.zeros(4), 2)
