"""
The landmark map and its fusion methods (numpy; numba optional, in ``compiled``).

``landmark_map.LandmarkMap`` fuses world-frame landmark observations by ID, with
gating and confirmation; ``records`` holds its typed records and pure functions;
``methods`` the fusion methods (product of Gaussians, covariance intersection, split
covariance intersection) behind one interface; ``source_sums`` split CI's per
(landmark, source) sums and their fold; ``compiled`` that fold compiled with numba,
loaded in the background.
"""
