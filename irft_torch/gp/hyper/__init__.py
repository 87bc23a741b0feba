"""Posteriors over the hyperparameters and the predictions that average over them: Laplace at the mode with
importance reweighting (``posterior``: proposals, weights and their Pareto k-hat in ``importance``, ``pareto``;
where the approximation fails, ``guard``), the closed-form log density of a batch of draws (``density``), pyro's
NUTS (``nuts``), and the finite Gaussian mixture over draws (``mixture``) that ``InverseRFT`` predicts with
(``predictions``)."""
