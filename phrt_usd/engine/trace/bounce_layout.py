"""The layout of the buffers ``trace_kernels.bounce`` reads and writes, declared once for
the kernel and for the bounce loop that owns the buffers (``paths``): plain constants, so
``paths`` reads them without compiling the kernel module (only kernel modules import
numba). The kernel cache's name hashes this file with the kernels
(``phrt_usd.kernels.SOURCE_MODULES``): the kernel reads these values as constants.
"""

from __future__ import annotations

#: Columns of the per-triangle material table ``bounce`` reads (``HitSurfaces.tri_table``,
#: (T, 5) float64): reflectivity F, the material's opacity α and ior, the element id
#: of a reflector triangle (-1: not a reflector), and 1 where the material has an albedo
#: texture (else 0).
TRI_F, TRI_ALPHA, TRI_IOR, TRI_REFLECTOR, TRI_TEXTURED = 0, 1, 2, 3, 4
TRI_COLUMNS = 5
#: Rows of ``bounce``'s live-ray state ``rays_i`` (int64): pixel slot, source, reflector
#: chain, refracted (0 / 1); its float32 rays ``rays_v``: direction, offset origin.
RAY_SLOT, RAY_SRC, RAY_CHAIN, RAY_REFRACTED = 0, 1, 2, 3
RAY_DIR, RAY_ORIGIN = 0, 1
RAY_ROWS = RAY_REFRACTED + 1
#: The call's gathered entries (``bounce`` appends one depth's to them). ``g_i`` (int64)
#: rows: environment slot, lit slot, lit source, lit triangle, reflector key; ``g_w``
#: (float64) rows: environment weight, lit weight; ``g_x`` (float64 (·, 3)): lit
#: position, lit geometric normal; ``g_v`` (float32 (·, 3)): environment direction, lit
#: shading normal, lit incoming direction, lit corner albedo; ``g_uv`` (float32): lit u,
#: v.
G_ENV_SLOT, G_LIT_SLOT, G_LIT_SRC, G_LIT_TRI, G_KEY = 0, 1, 2, 3, 4
G_ENV_W, G_LIT_W = 0, 1
G_LIT_POS, G_LIT_NG = 0, 1
G_ENV_DIR, G_LIT_NS, G_LIT_DIR, G_LIT_ALBEDO = 0, 1, 2, 3
G_LIT_U, G_LIT_V = 0, 1
#: Rows of g_i, g_w, g_x, g_v, g_uv.
G_ROWS = (G_KEY + 1, G_LIT_W + 1, G_LIT_NG + 1, G_LIT_ALBEDO + 1, G_LIT_V + 1)
#: ``tally`` (int64): the counts of gathered environment entries, lit hits, keys and lit
#: hits on textured materials, then the rays cast per source (S), then the longest
#: reflector chain per pixel slot.
T_ENV, T_LIT, T_KEYS, T_TEXTURED, T_SOURCES = 0, 1, 2, 3, 4
