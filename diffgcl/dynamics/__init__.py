"""Linear-Gaussian dynamics fits: autodiff linearisation through MJX, regression with a prior."""
