"""Board location in the log, the phase sign and the initial WoodModel guess (Nindel et al., thesis ch. 2,
§3.4–3.6), gathered from their rooms so that ``torch_appearance.rings.board`` keeps its names:

* :mod:`.board_estimate`: :class:`BoardEstimate`, :func:`estimate_board` (the projected tree centre, axis distance,
  tilt and ring scale from traced rings), :func:`find_centre_gap`;
* :mod:`.board_phase`: :func:`resolve_phase_sign`, :func:`lateness_profile_score`, :func:`choose_pith_side` (the
  growth direction), :func:`unwrap_phase`, :func:`split_at_pith_line` (the Gabor response split at the pith line);
* :mod:`.board_init`: :func:`initial_wood_model` (transform, ring scale and distortion of the first WoodModel).
"""
from .board_estimate import (BoardEstimate, _board_coords, _check_rings, _image_centre_mm, _resample,  # noqa: F401
                             _rotation_matrix, _transform, estimate_board, find_centre_gap)
from .board_init import initial_wood_model
from .board_phase import (choose_pith_side, lateness_profile_score, resolve_phase_sign, split_at_pith_line,
                          unwrap_phase)

__all__ = ["BoardEstimate", "estimate_board", "resolve_phase_sign", "initial_wood_model", "find_centre_gap",
           "lateness_profile_score", "choose_pith_side", "unwrap_phase", "split_at_pith_line"]
