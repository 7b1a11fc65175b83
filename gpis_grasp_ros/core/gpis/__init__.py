"""Gaussian process implicit surfaces with derivative observations (paper sections III-A, III-B and V-A).

The model, its computation and the hyperparameter bounds are described in docs/gpis-model.md.

* :mod:`.observations` - SDF values and gradient components the GP is trained on
* :mod:`.kernel`       - squared-exponential kernel and its derivatives
* :mod:`.basis`        - Kronecker eigenbasis of the prior on the grid
* :mod:`.likelihood`   - log marginal likelihood, its gradient and Fisher information
* :mod:`.hyperparameters` - maximum-likelihood C and l within bounds, warm start
* :mod:`.regression`   - :func:`fit_gpis`, :func:`posterior_from_data` (eqs. 1, 2)
* :mod:`.posterior`    - :class:`GpisPosterior`: samples, off-grid mean and gradient, centre of mass
* :mod:`.threads`      - BLAS thread limit of the fits
"""

from gpis_grasp_ros.core.gpis.hyperparameters import HyperparameterFit, fit_hyperparameters, hyperparameter_bounds
from gpis_grasp_ros.core.gpis.kernel import KernelParams
from gpis_grasp_ros.core.gpis.likelihood import fisher_information, negative_log_marginal_likelihood
from gpis_grasp_ros.core.gpis.observations import gradient_observations
from gpis_grasp_ros.core.gpis.posterior import GpisPosterior, center_of_mass, com_spread
from gpis_grasp_ros.core.gpis.regression import GpisParams, fit_gpis, posterior_from_data
from gpis_grasp_ros.core.gpis.threads import blas_threads

__all__ = [
    'GpisParams', 'GpisPosterior', 'HyperparameterFit', 'KernelParams', 'blas_threads', 'center_of_mass',
    'com_spread', 'fisher_information', 'fit_gpis', 'fit_hyperparameters', 'gradient_observations',
    'hyperparameter_bounds', 'negative_log_marginal_likelihood', 'posterior_from_data',
]
