"""Which reflectors each frame ray-traces: the paper's metrics (``metrics``), the trace-time
cost model (``cost_model``), the policies HEU1, HEU2, all, none, list (``policies``, their
memory as plain data in ``policy_memory``) and the Selection Graph (``selection_graph``)."""
