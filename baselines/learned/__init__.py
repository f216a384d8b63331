"""Learned baselines (DCP, PRNet, RPMNet, IDAM, PointNetLK, FMR, DeepGMR), each a network that
:class:`~src.models.module.RegistrationModule` trains (see :mod:`src.models.base`)."""
