"""Non-rigid registration of the template: optimal-step NICP (Amberg et al. 2007), its
sparse solver, its constraints (cloud, landmarks, silhouette edges) and the surface's
roughness. A shared helper: the coarse stage fits with it, and so does the fitting stage."""
