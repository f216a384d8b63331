"""Classical (non-learned) registration baselines: ICP, FGR, Symmetric ICP, Go-ICP.

Import a method's module directly or build it by name with
:func:`baselines.get_registrator` (``"icp"``, ``"fgr"``, ``"symmetric_icp"``, ``"goicp"``);
modules are imported lazily so that ``import baselines`` stays light.
"""
