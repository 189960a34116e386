"""Which reflectors each frame ray-traces: the paper's metrics and cost model,
the policies (HEU1, HEU2, all, none) and the Selection Graph."""
