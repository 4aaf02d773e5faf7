"""sep-burgers: a user's own plant for sep, packaged on its own (template).

`sep_burgers.plant.BurgersPlant` is the viscous Burgers equation on a ring with distributed
actuators; it meets sep's plant protocol structurally and imports numpy and scipy only. The
package registers it under the entry-point group ``sep.plants`` as ``burgers``.
"""
from sep_burgers.plant import BurgersPlant

__all__ = ["BurgersPlant"]
__version__ = "0.1.0"
