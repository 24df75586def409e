"""Slaves: what the master steps.  An FMU (FMI 2.0 or 3.0) is one kind (:mod:`.fmu`; a model-exchange
FMU is integrated inside its slave, :mod:`.model_exchange`); an analytic
linear system is another (:mod:`.linear`); the rig's hardware FMU is an FMU like any other.

A slave is described *before* it runs by a :class:`SlaveDescription` (:mod:`.description`); at run
time the master talks to it through the :class:`Slave` contract (:mod:`.slave`, its call order
there).  Variables of other FMI types than scalar Float64: :mod:`.types` and :mod:`.typedio`.
"""
from .description import SlaveDescription, Variable, describe_block, describe_fmu
from .fmu_slave import FmuSlave
from .linear import LinearSlave
from .model_exchange import ModelExchangeSlave
from .slave import FAILING, NativeEntry, Slave, Status

__all__ = ["FAILING", "FmuSlave", "LinearSlave", "ModelExchangeSlave", "NativeEntry", "Slave", "SlaveDescription",
           "Status", "Variable", "describe_block", "describe_fmu"]
