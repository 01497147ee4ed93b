"""Frame sources of the acquisition node: each a class with ``frames()`` yielding
:class:`~mtcw_core.frame.Frame` objects, made from :class:`~services.settings.AcquisitionSettings`.

=============  ======================================  ==================================
``source``     class                                   module
=============  ======================================  ==================================
``sim``        :class:`SimulatorSource`                :mod:`services.sources.simulator`
``replay``     :class:`ReplaySource`                   :mod:`services.sources.replay`
``scope``      :class:`~.scope.ScopeSource`            :mod:`services.sources.scope` (PyVISA)
``scope-sim``  the same, against a simulated MDO3      :mod:`services.sources.scope_sim`
=============  ======================================  ==================================

:func:`services.acquisition.make_source` picks one by name (or loads a ``module:Class``
plug-in). The scope modules import PyVISA only when a scope source is made.
"""

from .replay import ReplaySource
from .simulator import SimulatorSource

__all__ = ["ReplaySource", "SimulatorSource"]
