"""Which reflectors each frame ray-traces: the paper's metrics (``metrics``), the trace-time
cost model (``cost_model``), the policies HEU1, HEU2, all, none, list (``policies``, their
memory as plain data in ``policy_memory``), HEU3 (``benefit_policy``, registered with
``policies.make_policy`` by this import) and the Selection Graph (``selection_graph``)."""

from phrt_usd.select import benefit_policy  # noqa: F401  (registers heu3)
