"""Which reflectors each frame ray-traces: the paper's metrics (``metrics``), the trace-time
cost model (``cost_model``), the policies HEU2, all, none, list (``policies``, their
memory as plain data in ``policy_memory``), HEU1 (``heu1_policy``) and HEU3
(``benefit_policy``), both registered with ``policies.make_policy`` by this import, and
the Selection Graph (``selection_graph``)."""

from phrt_usd.select import benefit_policy, heu1_policy  # noqa: F401  (register heu3, heu1)
