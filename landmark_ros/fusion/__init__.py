"""
The landmark map and its fusion methods (numpy; numba optional, in ``compiled``).

``landmark_map.LandmarkMap`` fuses world-frame landmark observations by ID, with
gating and confirmation; ``methods`` holds the fusion methods (product of Gaussians,
covariance intersection, split covariance intersection) behind one interface;
``source_sums`` the per-(landmark, source) sums of split CI and their fold;
``compiled`` the same fold compiled with numba, loaded in the background.
"""
