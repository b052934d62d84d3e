"""The node graph: one module per process plus the small runtime they share.

Runtime: :mod:`nodes.bus` (broker, topic framing), :mod:`nodes.node` (node base class),
:mod:`nodes.params` (parameters), :mod:`nodes.launch` (launch files).
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
}

__doc__ += "".join(f"\n* ``{k}``: :mod:`{v}`" for k, v in NODE_TYPES.items())
