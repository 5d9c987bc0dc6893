"""Trunk detection from a 3D lidar point cloud: ground, height band, clusters, cylinder fits.

The 3D counterpart of ``jaxslam.detect.detect_trunks``. Geiser et al., "Practical
Implementation of FastSLAM for Forestry Robot" (ICAROB 2023) clip the cloud in height to drop
ground and canopy, cluster the rest (Euclidean clustering) and fit a cylinder to each cluster by
RANSAC; the tree is where the cylinder's axis meets a horizontal plane. Yang et al., "A 3D Lidar
SLAM System Based on Semantic Segmentation for Rubber-Tapping Robot" (Forests 2023) fit cylinders
to trunk points the same way and report a DBH error of 0.57 cm. ``clip_points_by_height`` in
``jaxslam.detect`` instead flattens a height slice into a 2D scan; there a leaning trunk's centre
depends on the slice and its horizontal section is an ellipse of semi-axes r and r / cos(lean),
so circle fits get both the position and the diameter wrong.

Frame: the sensor frame with z up. A tilted sensor should be levelled upstream: the ground
model absorbs a tilt of a few degrees as a slope, but every trunk then leans by the tilt.
Every step keeps fixed shapes, so the whole pipeline runs under ``jit`` and ``vmap`` over scans
(B clouds of N points, padded with ``valid = False``). Dimensions: N points, S = G x G ground
cells, C cluster slots (``max_clusters``), P points per cluster (``cluster_points``), H
hypotheses per cluster (``num_hypotheses``), K output rows (``max_obs``).

Pipeline:
  1. Points. A point is used when ``valid``, finite, farther than ``min_range`` and inside the
     square |x|, |y| < ``max_range`` (the extent of both grids).
  2. Ground (``estimate_ground``): a robust local-plane smoother, not a flat-ground model.
     a. Seeds: on a G x G grid of ``ground_cell`` cells, each cell's point at the
        ``ground_quantile`` of its heights (sorted index floor(q (n - 1))); one seed per cell.
     b. Robust LOWESS (Cleveland, "Robust Locally Weighted Regression and Smoothing
        Scatterplots", JASA 1979) of the seeds: at a query q the local plane
        z = alpha + beta (x - q_x) + gamma (y - q_y) minimises
        sum_k K_k rho_k (z_k - alpha - beta dx_k - gamma dy_k)^2 with the Gaussian kernel
        K_k = exp(-|c_k - q|^2 / (2 h^2)), h = ``ground_bandwidth``. The robustness weights
        rho_k are refit ``ground_iterations`` times from the residual e_k = z_k - alpha(c_k) of
        each seed against the fit at its own place: rho_k = T(e_k / s) above the surface and
        T(e_k / (3 s)) below (T(u) = (1 - u^2)^2 for |u| < 1, else 0: Tukey's biweight), the
        scale s shrinking geometrically from 1 m to ``ground_tol``. The asymmetry makes the
        surface the lower envelope (seeds on trunks, bushes and walls sit above the ground;
        low outliers are rare in lidar data).
     c. Ground points: those within ``ground_tol`` of that surface, except under objects:
        points from ``ground_tol`` to ``band_max`` above it (trunks, bushes, walls; not the
        canopy) mark their cell of the cluster grid (step 4) and its 8 neighbours, and points
        there are not ground (a trunk's lowest ring, a few cm above the ground, would otherwise
        lift the ground at its base by millimetres). Their per-cell moments
        (count, sums of dx, dy, z, dx^2, dx dy, dy^2, dx z, dy z about the cell centre) feed the
        same smoother once more (kernel on the cell centres, rho = 1), which removes the low
        bias of the quantile seeds under noise. The ground model is this final local plane at
        each cell centre; a point's ground height is its cell's plane at its (x, y) (piecewise
        planar: exact on a plane, steps of the curvature bias between cells otherwise).
     Limits: the local plane is exact on planar ground (any slope) and biased on curved
     ground: on a bowl z = c (x^2 + y^2) by about c (sx^2 + sy^2), s the spread of the ground
     points in the kernel (at most ~h; lidar rings make it uneven). Measured with the test
     sensor (16 rings, 1 m above the ground): c = 0.005 /m (curvature 0.01 /m) puts the
     breast-height point 3 cm too high and 5 mm off horizontally for leans up to 15 degrees;
     c = 0.02 /m (slope 0.32 at 8 m), 25 cm and 4 cm; a local quadratic would remove this;
     cells are extrapolated from neighbours within ~2 h, so the ground under a robot whose
     lidar cannot see it nearby (a VLP-16 at 1 m sees no ground within 3.7 m) is the plane of
     the ground farther out; dense understory that hides the ground over more than ~h becomes
     the ground; overhangs (a cell's lowest return not on the ground anywhere nearby) bias it up.
  3. Height band: the points with height above their ground in [``band_min``, ``band_max``]
     (default 0.5-3 m: above the ground, stumps and low shrubs, below the crowns).
  4. Clusters (``cluster_points_2d``): the band's XY projection rasterised on a grid of
     ``cluster_cell`` cells; occupied cells that touch (8-neighbourhood) form a cluster, found by
     min-label propagation with pointer jumping until nothing changes (each cell's label ends as
     the smallest flat index in its component). Points less than one cell apart always join,
     points more than 2 sqrt(2) cells apart never. Clusters with at least ``min_points`` points
     are ranked by the horizontal range of their centroid and the ``max_clusters`` nearest are
     fitted; FARTHER CLUSTERS ARE DROPPED (``Trunks3D.num_clusters`` counts them all). Each
     cluster's fit uses at most ``cluster_points`` of its points: all of them when it has that
     many or fewer, otherwise the points at ranks floor(j n / P), j < P, of its points in input
     order (an even spread over the scan's rings).
  5. Cylinders (``fit_cylinders``). A cylinder is its axis crossing (x0, y0) of the plane
     z = z_ref (the cluster's mean height), the axis slopes (a, b) (direction
     u = (a, b, 1) / |(a, b, 1)|, lean = atan(|(a, b)|)) and its radius r; the residual of a
     point p is e = |(p - p0) x u| - r, p0 = (x0, y0, z_ref).
     a. Hypotheses (RANSAC: Fischler and Bolles, "Random Sample Consensus", CACM 1981): H per
        cluster. Two are deterministic: a vertical axis through the Kasa circle (Kasa, "A
        Circle Fitting Procedure and its Error Analysis", IEEE TIM 1976) of all points, and the
        axis through the Kasa centres of the lower and upper thirds of the cluster's height
        range. The other H - 2
        draw an anchor point in the lower third and two points within ``ring_thickness`` of its
        height (one lidar ring: a horizontal section of the cylinder, an ellipse close to a
        circle for small leans), the same in the upper third; the axis joins the two
        three-point circle centres, r is the mean distance of the six points to it. A
        hypothesis is kept when its radius is at most 2 ``max_radius`` and its lean at most
        3 ``max_lean`` (capped at 70 degrees), so that too wide and too leaning trunks still fit
        and are rejected below for the right reason; the one with the most inliers
        (|e| < ``inlier_tol``) wins (ties: the lower index, so the deterministic ones first).
     b. Refinement: ``refine_rounds`` rounds of taking the inliers of the current cylinder and
        ``lm_iterations`` Levenberg-Marquardt steps on sum_inliers e^2 (per-point gradients by
        ``jax.grad``; a step is kept when the cost does not rise, the damping mu is divided by
        10 on success and multiplied by 10 otherwise).
  6. Position. The axis meets the ground at its base: z_b solves z = g(x(z), y(z)) where
     (x(z), y(z)) is the axis at height z and g the plane of the ground cell under the current
     crossing (three line-plane intersections, exact on planar ground). The trunk's position
     is the axis at breast height z_b + ``breast_height`` (1.3 m vertically above the base,
     i.e. 1.3 / cos(lean) along the stem), reported as horizontal range and bearing in the
     sensor frame, and the radius r = DBH / 2 (perpendicular to the axis).
  7. Rejections (masks in ``CylinderFits``): too few points (fewer than ``min_points`` in the
     cluster or among the inliers), radius outside [``min_radius``, ``max_radius``], lean over
     ``max_lean``, bushes (inlier ratio below ``min_inlier_ratio``), walls (the cross-section,
     the points moved along the axis onto the plane z = z_ref, spans more than ``max_width`` along
     its principal direction, or is flat: its second-to-first principal variance ratio is below
     ``min_flatness``; a seen half-circle gives ~0.15, a plane only its noise), and fits that are
     not trunks seen from outside (no hypothesis, non-finite values, or the axis nearer the
     sensor than the points' centroid).
  8. The ``max_obs`` nearest accepted trunks become ``Observations`` (as ``detect_trunks``).

Modules: ``grid`` (the square grids), ``solve`` (small unrolled linear solves), ``ground``
(step 2), ``clusters`` (step 4), ``cylinders`` (step 5), ``measure`` (steps 6 and 7) and
``detector`` (steps 1, 3 and 8: ``fit_trunks_3d``, ``detect_trunks_3d``).
"""
from jaxslam.detect3d.clusters import cluster_points_2d, connected_components, gather_clusters
from jaxslam.detect3d.cylinders import (cylinder_hypotheses, cylinder_residual, fit_cylinders,
                                        levenberg_marquardt)
from jaxslam.detect3d.detector import Trunks3D, detect_trunks_3d, fit_trunks_3d
from jaxslam.detect3d.grid import cell_centres, grid_cells, grid_size
from jaxslam.detect3d.ground import (Ground3D, estimate_ground, footprint, ground_seeds,
                                     local_planes, plane_height, point_moments, seed_planes)
from jaxslam.detect3d.measure import CylinderFits, axis_base, cross_section, measure_cylinders
from jaxslam.detect3d.solve import solve_sym3, spd_solve

__all__ = [
    "CylinderFits", "Ground3D", "Trunks3D", "axis_base", "cell_centres", "cluster_points_2d",
    "connected_components", "cross_section", "cylinder_hypotheses", "cylinder_residual",
    "detect_trunks_3d", "estimate_ground", "fit_cylinders", "fit_trunks_3d", "footprint",
    "gather_clusters", "grid_cells", "grid_size", "ground_seeds", "levenberg_marquardt",
    "local_planes", "measure_cylinders", "plane_height", "point_moments", "seed_planes",
    "solve_sym3", "spd_solve",
]
