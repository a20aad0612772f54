"""Phase 3 (Sec. 3.5, Appendices A, B, F): the synchronized object-time language field.

On a frozen Phase 2 run (read through `sync4d.runs.load_run`, never by building a trainer):
object crops and occlusion-aware visibility, image-text embeddings behind one encoder
interface, 28-D kinematic features, a per-object closed-form ridge map, blending and temporal
smoothing, and queries that answer which object and when. Evaluation follows Appendix F.
"""

from sync4d.lazy import lazy_exports

#: Public names and the module that defines each, imported on first use (a query needs neither
#: torch nor the rasterizer, so `sync4d.phase3.query` stays light).
_EXPORTS = {
    "Encoder": "encoders.encoder", "EncoderError": "encoders.encoder",
    "load_encoder": "encoders.encoder",
    "Field": "store", "FieldError": "store", "load_field": "store",
    "build_field": "build", "QueryError": "query", "answer": "query", "query": "query",
}  # fmt: skip

__all__, __getattr__ = lazy_exports(__name__, _EXPORTS)
