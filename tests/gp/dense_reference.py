"""The I-RFT model written plainly, as the paper writes it: explicit W (T x TM), explicit K
(TM x TM), torch Cholesky. Independent of the package's operator, kernel and gpytorch."""

import math

import torch


def embed(beta, gamma):
    return torch.stack([torch.sin(2 * beta), torch.cos(2 * beta), torch.sin(gamma), torch.cos(gamma)], -1)


def k_dense(th1, th2, lengthscale, outputscale):
    """th (n, 2) angle pairs -> (n1, n2) ARD RBF on the embedding, written with explicit differences."""
    a = embed(th1[:, 0], th1[:, 1]) / lengthscale
    b = embed(th2[:, 0], th2[:, 1]) / lengthscale
    d2 = ((a[:, None, :] - b[None, :, :]) ** 2).sum(-1)
    return outputscale * torch.exp(-0.5 * d2)


def W_dense(weight):
    """(T, M) weights -> explicit (T, T*M) block matrix W[t, t*M + m] = w[t, m]."""
    T, M = weight.shape
    W = torch.zeros(T, T * M, dtype=weight.dtype)
    for t in range(T):
        W[t, t * M:(t + 1) * M] = weight[t]
    return W


def axis_reference(contacts, y, weight, lengthscale, outputscale, noise, mean=None):
    """MLL (gpytorch's normalization: per observation), and a function for posteriors."""
    th = torch.stack([contacts.beta.reshape(-1), contacts.gamma.reshape(-1)], -1)
    W = W_dense(weight)
    K = k_dense(th, th, lengthscale, outputscale)
    S = W @ K @ W.T + noise * torch.eye(W.shape[0], dtype=W.dtype)
    L = torch.linalg.cholesky(S)
    r = y - (0 if mean is None else mean)
    alpha = torch.cholesky_solve(r[:, None], L)[:, 0]
    T = y.shape[0]
    mll = -0.5 * r @ alpha - torch.log(torch.diagonal(L)).sum() - 0.5 * T * math.log(2 * math.pi)

    def map_posterior(th_star, mean_star=None):
        ks = k_dense(th_star, th, lengthscale, outputscale) @ W.T  # k(theta*, Theta) W^T
        mu = ks @ alpha + (0 if mean_star is None else mean_star)
        var = outputscale - (ks * torch.cholesky_solve(ks.T, L).T).sum(-1)
        return mu, var

    def force_posterior(c_star, w_star, mean_star=None, full=False):
        """Mean and variance (or, with ``full``, the joint covariance) of the weighted sums of c_star."""
        th_s = torch.stack([c_star.beta.reshape(-1), c_star.gamma.reshape(-1)], -1)
        Ws = W_dense(w_star)
        Kss = Ws @ k_dense(th_s, th_s, lengthscale, outputscale) @ Ws.T
        Ksx = Ws @ k_dense(th_s, th, lengthscale, outputscale) @ W.T
        mu = Ksx @ alpha + (0 if mean_star is None else mean_star)
        if full:
            return mu, Kss - Ksx @ torch.cholesky_solve(Ksx.T, L)
        var = torch.diagonal(Kss) - (Ksx * torch.cholesky_solve(Ksx.T, L).T).sum(-1)
        return mu, var

    return mll / T, map_posterior, force_posterior


def truncation_gaps(basis, lengthscale, n=300, seed=1):
    """(A,) the largest |k - k_basis| per map over n random angle pairs of the canonical square: the ARD RBF on the
    embedding (unit variance, ``embed``) against the Fourier ``basis``'s truncated kernel at ``lengthscale``
    (A, 1, 4)."""
    g = torch.Generator().manual_seed(seed)
    b1, b2, g1, g2 = ((torch.rand(n, generator=g, dtype=torch.float64) - 0.5) * math.pi for _ in range(4))
    ls = lengthscale[:, 0]  # (A, 4)
    exact = torch.exp(-0.5 * ((embed(b1, g1)[None] - embed(b2, g2)[None]) / ls[:, None]).pow(2).sum(-1))  # (A, n)
    Sb, Sg = basis.coefficients(lengthscale)
    pb1, pg1 = basis.features(b1, g1)
    pb2, pg2 = basis.features(b2, g2)
    approx = torch.einsum("ni,aij,nj->an", pb1, Sb, pb2) * torch.einsum("ni,aij,nj->an", pg1, Sg, pg2)
    return (exact - approx).abs().amax(-1)
