"""Studies of how this framework was built and validated: one folder each, with its README and results. The product never imports them."""
