"""Image thresholds more than one test module holds the renderer to, each declared once
with its reason."""

#: Mean FLIP allowed between hybrid with every reflector traced and the rt reference
#: (the renderer's invariant, docs/design.md: hybrid with heuristic ``all`` renders what
#: rt renders).
HYBRID_VS_RT_FLIP = 0.02
