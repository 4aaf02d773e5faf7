"""sep_plant: part of sep (separation-based, data-driven LQG for large partially observed systems): plant protocol, plants, scenarios, topic contract.

``__version__`` is the one version of sep (sep_estimator and sep_control import it from here);
the literal copies in the three setup.py and package.xml files must equal it (a test checks).
"""

__version__ = "0.8.0"
