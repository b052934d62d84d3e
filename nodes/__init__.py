"""The node graph: one module per process plus the small runtime they share.

Runtime: :mod:`nodes.runtime.bus` (broker, topic framing), :mod:`nodes.runtime.node` (node base class),
:mod:`nodes.runtime.params` (parameters), :mod:`nodes.runtime.launch` (launch files).
Nodes (``python -m nodes.<module> name:=value ...``, or by type name in a launch file):
"""

#: node type (as written in launch files) -> module that runs it
NODE_TYPES: dict[str, str] = {
    "radar_driver": "nodes.radar_driver",
    "vio_driver": "nodes.vio_driver",
    "synchronizer": "nodes.synchronizer",
    "template_builder": "nodes.template_builder",
    "solver": "nodes.solver",
    "visualizer": "nodes.visualizer",
    "recorder": "nodes.recorder",
    "player": "nodes.player",
    "foxglove_bridge": "nodes.foxglove_bridge",
}

#: node types whose end (status 0) is part of their job: a player at the end of its log, a
#: driver whose backend has no more samples (simulation, files). By default the launcher lets
#: them finish. Any other node ending while the graph runs would stall it (the solver would wait
#: for measurements forever), so by default the launcher stops the graph then (status 1).
#: A launched node stopped by a signal that is not the launcher's exits 128 + signal, so that is
#: never taken for a finished job.
FINISHING_TYPES = frozenset({"player", "radar_driver", "vio_driver"})

__doc__ += "".join(f"\n* ``{k}``: :mod:`{v}`" for k, v in NODE_TYPES.items())
