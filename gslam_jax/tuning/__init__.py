"""Parameter search and tuning: batched search over designs (``search``), strategies on top
of it (``strategies``), a Dask cluster (``distributed``), gradient tuning with optax
(``gradient``) and the maximum-likelihood motion noise of a log with ground truth
(``motion_fit``)."""
