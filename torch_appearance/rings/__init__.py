"""Growth-ring analysis of wood photographs: synthetic boards, orientation fields, curved Gabor filters, ring
tracing and board-location estimation (Nindel et al., thesis ch. 2)."""
from .synthetic import synthetic_board
from .orientation import orientation_field, orientation_from_phase
from .gabor import CurvedGaborFilter, GaborResult, curved_gabor, curved_gabor_response
from .tracing import trace_rings
from .board import (BoardEstimate, choose_pith_side, estimate_board, initial_wood_model, lateness_profile_score,
                    resolve_phase_sign)

__all__ = ["synthetic_board", "orientation_field", "orientation_from_phase", "GaborResult", "curved_gabor",
           "CurvedGaborFilter", "curved_gabor_response",
           "trace_rings", "BoardEstimate", "estimate_board", "initial_wood_model", "resolve_phase_sign",
           "choose_pith_side", "lateness_profile_score"]
from .dendro import (RingBoundaries, detect_core_boundaries, detect_transect_boundaries, match_boundaries,
                     ring_widths_mm)

__all__ += ["RingBoundaries", "detect_core_boundaries", "detect_transect_boundaries", "match_boundaries",
            "ring_widths_mm"]
from .disc import DiscBoundaries, detect_disc_boundaries
from .coorecorder import PosFile, read_pos, write_pos
from .tucson import RingSeries, read_rwl, write_rwl
from .pith import PithEstimate, detect_pith

__all__ += ["DiscBoundaries", "detect_disc_boundaries", "PosFile", "read_pos", "write_pos", "RingSeries", "read_rwl",
            "write_rwl", "PithEstimate", "detect_pith"]
