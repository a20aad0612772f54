"""Phase 3 (Sec. 3.5, Appendices A, B, F): the synchronized object-time language field.

On a frozen Phase 2 run (read through `sync4d.runs.load_run`, never by building a trainer):
object crops and occlusion-aware visibility, image-text embeddings behind one encoder
interface, 28-D kinematic features, a per-object closed-form ridge map, blending and temporal
smoothing, and queries that answer which object and when. Evaluation follows Appendix F.
"""

from sync4d.phase3.build import Field, FieldError, build_field, load_field
from sync4d.phase3.encoder import Encoder, EncoderError, load_encoder
from sync4d.phase3.query import QueryError, answer, query

__all__ = [
    "Encoder",
    "EncoderError",
    "Field",
    "FieldError",
    "QueryError",
    "answer",
    "build_field",
    "load_encoder",
    "load_field",
    "query",
]
