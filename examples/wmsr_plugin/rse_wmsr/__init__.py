"""W-MSR resilient consensus on local observers' estimates, an algorithm plugin of rse.

* :mod:`rse_wmsr.wmsr`: the maths (the W-MSR update, the modal design, the estimator);
* :mod:`rse_wmsr.plugin`: the plugin module rse finds through the ``rse.algorithms`` entry
  point (``[estimator] algorithm = "wmsr"``).
"""

__version__ = "0.1.0"
