"""The global policy of GPS: a Gaussian policy on observations and its MDGPS S-step.

* :mod:`diffgcl.policies.network` — :class:`~diffgcl.policies.network.GaussianPolicy`
  (``init`` / ``mean_action`` / ``sample_action`` / ``log_prob``),
  :class:`~diffgcl.policies.network.PolicyConfig`, the frozen observation normaliser;
* :mod:`diffgcl.policies.mdgps` — the S-step (precision-weighted regression onto the local
  controllers, the closed-form variance) and the policy's autodiff linearisation.

Algorithms that use them: :mod:`diffgcl.algorithms.mdgps` (MDGPS with a known cost, and the
policy phases shared with rGCL), :mod:`diffgcl.algorithms.rgcl` (``RGCLConfig.policy``) and
:mod:`diffgcl.algorithms.bc` (behaviour cloning, the baseline).
"""
