"""Logarithmic depth: one depth test from the street to orbit in one target.

A frame that holds the globe and the terrain spans centimetres to tens of thousands of
kilometres; the projection's own depth (hyperbolic in the distance, 24 bits) cannot hold both
ends, whatever its clip planes. A fragment's depth is instead the log of its distance along the
view axis (``1 / gl_FragCoord.w``), the same mapping for every pass whatever its camera's clip
planes: relative precision about 1e-6 everywhere (a centimetre at 10 km). The top of the range,
``BAND``, is kept for surfaces that only fill what nothing else drew (the globe under the
terrain's data), ordered there among themselves by the same log.
"""

from __future__ import annotations

__all__ = ["BAND", "LOG_DEPTH_FAR", "LOG_DEPTH_GLSL", "with_log_depth"]

#: The farthest distance (m) the mapping reaches, well past the Earth seen from the Moon.
LOG_DEPTH_FAR = 1.0e9
#: The depth range's top kept for surfaces drawn behind everything else.
BAND = 2.0**-10

LOG_DEPTH_GLSL = f"""
const float LOG_DEPTH_SCALE = {(1.0 - BAND):.9f} / log2(1.0 + {LOG_DEPTH_FAR:.1f});
const float LOG_DEPTH_BAND = {BAND:.9f};
// the log of the distance along the view axis (w = 1 / gl_FragCoord.w), below the band
float log_depth(float w) {{ return log2(1.0 + max(w, 0.0)) * LOG_DEPTH_SCALE; }}
// the same, in the band kept for what fills only where nothing else drew
float behind_depth(float w) {{ return 1.0 - LOG_DEPTH_BAND + LOG_DEPTH_BAND * log_depth(w); }}
"""

_MAIN = "void main() {"


def with_log_depth(fragment: str) -> str:
    """``fragment`` writing the logarithmic depth of its fragments (``LOG_DEPTH`` defined)."""
    if fragment.count(_MAIN) != 1:
        raise ValueError("a fragment shader with log depth needs exactly one 'void main() {'")
    head, body = fragment.split(_MAIN)
    return (
        head
        + "#define LOG_DEPTH\n"
        + LOG_DEPTH_GLSL
        + _MAIN
        + "\n    gl_FragDepth = log_depth(1.0 / gl_FragCoord.w);"
        + body
    )
