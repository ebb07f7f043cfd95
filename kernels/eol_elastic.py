"""Warp kernel of EoL elastic forces and lumped masses from material quadrature points.

The body is integrated at material quadrature points i (material volume w_i, fixed in z, found in
the intermediate domain at y_i by Algorithm 2 each step). At y_i the reference map gives
G = grad_y z, the Eulerian deformation gradient F_2 = G^-1 and, with the Lagrangian deformation
gradient F_L (I in the rigid frame's axes; A for affine coordinates, Eq. 9), the total
F = F_L G^-1; with plasticity (Eq. 34) the elastic part is F_e = F F_p^-1, F_p^-1 stored per
material point (Sec. 3.7: in the material domain).

Forces are the weak form of the momentum balance on a trilinear velocity field w(y) = sum_s
w_s Phi_s(y) (w the material's velocity in F_L's axes): the elastic power is
int_z P(F_e) : grad_z w F_p^-1 dz with grad_z w = grad_y w G^-1, so

    g_s = - sum_i w_i P(F_e) F_p^-T G^-T grad Phi_s(y_i)         (Cauchy stress form)
    m_s = sum_i rho w_i Phi_s(y_i)                                (lumped mass, paper: M_2 diagonal)

Affine velocities are reproduced exactly by trilinear nodes, so sum_s g_s (y_s, 1)^T is exactly
-dV/d(A, b): the forces on the Lagrangian coordinates are consistent with the nodal ones (what the
redundancy of Eq. 18-22 requires). Constitutive law: compressible Neo-Hookean,
W = mu/2 (tr F^T F - 3) - mu ln J + lam/2 (ln J)^2, P = mu (F - F^-T) + lam ln J F^-T: zero
energy and stress for any rotation. Float64 throughout: G is a difference of nearby absolute
coordinates (z_s - z_t ~ h), where float32 would lose the strain to cancellation.
"""

from __future__ import annotations

import warp as wp

from wsim.kernels.eol_grid import (
    Grid,
    cell_of,
    corner_gradient,
    corner_weight,
    gradient_in_cell,
    grid_coordinates,
    local_coordinates,
)

# dt R_s / m_s above which a node's viscosity is cut (kernel ``viscous_forces``): nodes of full cells
# have 2.0-2.7 at the viscous cap, where dt lambda_max = 2/3 (tests/test_eol_foundation.py)
VISCOUS_ROW_LIMIT = wp.constant(wp.float64(3.0))

# below this det F_e the element is treated as (nearly) inverted: ln J is evaluated at the floor
J_FLOOR = 1.0e-6


@wp.func
def neo_hookean(F: wp.mat33d, mu: wp.float64, lam: wp.float64) -> wp.mat33d:
    """First Piola-Kirchhoff stress P(F) of compressible Neo-Hookean."""
    J = wp.max(wp.determinant(F), wp.float64(J_FLOOR))
    F_invT = wp.transpose(wp.inverse(F))
    return mu * (F - F_invT) + lam * wp.log(J) * F_invT


@wp.func
def neo_hookean_energy(F: wp.mat33d, mu: wp.float64, lam: wp.float64) -> wp.float64:
    """Energy density W(F) of compressible Neo-Hookean [J/m^3]."""
    logJ = wp.log(wp.max(wp.determinant(F), wp.float64(J_FLOOR)))
    half = wp.float64(0.5)
    return half * mu * (wp.ddot(F, F) - wp.float64(3.0)) - mu * logJ + half * lam * logJ * logJ


@wp.kernel
def zero_nodes(forces: wp.array3d(dtype=wp.vec3d), mass: wp.array3d(dtype=wp.float64),
               energy: wp.array(dtype=wp.float64)):
    """forces = 0, mass = 0 (node arrays) and energy = 0: the accumulators of a force pass in one
    launch instead of three memsets."""
    i, j, k = wp.tid()
    forces[i, j, k] = wp.vec3d()
    mass[i, j, k] = wp.float64(0.0)
    if i == 0 and j == 0 and k == 0:
        energy[0] = wp.float64(0.0)


#: threads of a ``sample_forces`` block (a tiled launch: the block sums its energy, one atomic)
FORCES_BLOCK = 128


@wp.kernel
def sample_forces(
    z: wp.array3d(dtype=wp.vec3d),
    grid: Grid,
    y: wp.array(dtype=wp.vec3d),
    volume: wp.array(dtype=wp.float64),
    Fp_inv: wp.array(dtype=wp.mat33d),
    plastic: int,
    F_L: wp.mat33d,
    mu: wp.float64,
    lam: wp.float64,
    rho: wp.float64,
    forces: wp.array3d(dtype=wp.vec3d),
    mass: wp.array3d(dtype=wp.float64),
    energy: wp.array(dtype=wp.float64),
):
    """One thread per material point: scatter g_s and m_s to its cell's 8 nodes; the block's sum of
    w W is added to energy once (tiled; an atomic per point on the one address serialized ~136k
    adds a step at 32^3)."""
    block, lane = wp.tid()
    i = block * wp.block_dim() + lane
    e = wp.float64(0.0)
    if i < volume.shape[0]:
        h = grid.h
        g = grid_coordinates(z, y[i], grid)
        cell = cell_of(z, g)
        t = local_coordinates(g, cell)
        G_inv = wp.inverse(gradient_in_cell(z, cell, t, h))
        F = F_L * G_inv
        S = wp.identity(n=3, dtype=wp.float64)
        if plastic != 0:
            S = Fp_inv[i]
        Fe = F * S
        P = neo_hookean(Fe, mu, lam)
        stress = volume[i] * P * wp.transpose(S) * wp.transpose(G_inv)
        for c in range(8):
            a = cell[0] + c // 4
            b = cell[1] + (c // 2) % 2
            d = cell[2] + c % 2
            wp.atomic_add(forces, a, b, d, -(stress * corner_gradient(c, t, h)))
            wp.atomic_add(mass, a, b, d, rho * volume[i] * corner_weight(c, t))
        e = volume[i] * neo_hookean_energy(Fe, mu, lam)
    total = wp.tile_sum(wp.tile(e))
    if lane == 0:
        wp.atomic_add(energy, 0, total[0])


@wp.kernel
def cell_fill(
    z: wp.array3d(dtype=wp.vec3d),
    grid: Grid,
    y: wp.array(dtype=wp.vec3d),
    volume: wp.array(dtype=wp.float64),
    filled: wp.array3d(dtype=wp.float64),
):
    """One thread per material point: add its material volume to the cell it lies in."""
    i = wp.tid()
    cell = cell_of(z, grid_coordinates(z, y[i], grid))
    wp.atomic_add(filled, cell[0], cell[1], cell[2], volume[i])


@wp.kernel
def hourglass_forces(
    z: wp.array3d(dtype=wp.vec3d),
    filled: wp.array3d(dtype=wp.float64),
    h: wp.float64,
    full: wp.float64,
    F_L: wp.mat33d,
    stiffness: wp.float64,
    forces: wp.array3d(dtype=wp.vec3d),
    energy: wp.array(dtype=wp.float64),
):
    """One thread per cell: hourglass control of a cell its material points under-integrate.

    The material points of a partly filled cell (a thin part: an ear, a flap, a corner) see the
    trilinear reference map z only through its gradient at those few points, so the 8 corners
    keep non-affine modes that change no sample's F (the hourglass modes of reduced integration,
    Flanagan & Belytschko 1981). Their stress then pushes those corners with a force nothing
    relaxes; light thin-part nodes ring at several m/s, and a bunny that lands at 3.7 m/s without
    this control diverged 2.4 s after the landing (issue 16 item 6). With d_c = h (p_c - 1/2) the
    corner offsets, the affine fit of the corner values is z_bar + G d_c with
    G = sum_c z_c (x) d_c / (2 h^2); the residual r_c = z_c - z_bar - G d_c is the hourglass part
    (it holds no affine field). The material at corner c sits F r_c (F = F_L G^-1) from where the
    fit puts it, and the penalty

        E = k / 2 sum_c |F r_c|^2 / h^2,   k = stiffness V (1 - V / full)

    (``stiffness`` [Pa]: the body's ``hourglass`` times mu; V the cell's material volume; ``full``
    the volume at which the quadrature integrates the cell fully, 0 for one point per cell, whose
    cells all under-integrate) pushes corner c by
    f_c = k F r_c / h^2 (advection moves z_c by -G dy). The forces sum to zero and have no moment
    (r is orthogonal to every affine field of the corners), so momentum is untouched; a filled
    cell (V = full) gets none, so fully integrated material keeps its stiffness."""
    i, j, k = wp.tid()
    V = filled[i, j, k]
    if V <= wp.float64(0.0):
        return
    weight = V
    if full > wp.float64(0.0):
        weight = V * wp.max(wp.float64(1.0) - V / full, wp.float64(0.0))
    if weight <= wp.float64(0.0):
        return
    half = wp.float64(0.5)
    zbar = wp.vec3d()
    G = wp.mat33d()
    for c in range(8):
        zc = z[i + c // 4, j + (c // 2) % 2, k + c % 2]
        d = h * wp.vec3d(wp.float64(c // 4) - half, wp.float64((c // 2) % 2) - half, wp.float64(c % 2) - half)
        zbar += zc
        G += wp.outer(zc, d)
    zbar = zbar / wp.float64(8.0)
    G = G / (wp.float64(2.0) * h * h)
    if wp.abs(wp.determinant(G)) < wp.float64(J_FLOOR):
        return  # a degenerate cell: no frame to measure the residual in
    F = F_L * wp.inverse(G)
    kh = stiffness * weight / (h * h)
    e = wp.float64(0.0)
    for c in range(8):
        zc = z[i + c // 4, j + (c // 2) % 2, k + c % 2]
        d = h * wp.vec3d(wp.float64(c // 4) - half, wp.float64((c // 2) % 2) - half, wp.float64(c % 2) - half)
        dy = F * (zc - zbar - G * d)
        wp.atomic_add(forces, i + c // 4, j + (c // 2) % 2, k + c % 2, kh * dy)
        e += wp.dot(dy, dy)
    wp.atomic_add(energy, 0, half * kh * e)


@wp.kernel
def viscous_row_bound(
    grid: Grid,
    w: wp.array3d(dtype=wp.vec3d),
    y: wp.array(dtype=wp.vec3d),
    volume: wp.array(dtype=wp.float64),
    F_L_inv: wp.mat33d,
    eta: wp.float64,
    bound: wp.array3d(dtype=wp.float64),
):
    """Gershgorin bound of the Kelvin-Voigt stiffness K (f = -K w, kernel ``viscous_forces``):
    R_s = sum_t ||K_st|| <= sum_i 2 eta w_i |b_s| sum_c |b_c| with b_c = F_L^-T grad_y Phi_c(y_i),
    since K_st = sum_i eta w_i ((b_s . b_t) I + b_t b_s^T) over the points i in both supports.
    Forward Euler on M w' = -K w is stable where dt R_s / m_s <= 2 for every node s. ``w`` only
    gives the grid's node shape; ``bound`` is accumulated (zero it first)."""
    i = wp.tid()
    h = grid.h
    g = grid_coordinates(w, y[i], grid)
    cell = cell_of(w, g)
    t = local_coordinates(g, cell)
    FT = wp.transpose(F_L_inv)
    total = wp.float64(0.0)
    for c in range(8):
        total += wp.length(FT * corner_gradient(c, t, h))
    for c in range(8):
        wp.atomic_add(bound, cell[0] + c // 4, cell[1] + (c // 2) % 2, cell[2] + c % 2,
                      wp.float64(2.0) * eta * volume[i] * wp.length(FT * corner_gradient(c, t, h)) * total)


@wp.kernel
def viscous_forces(
    w: wp.array3d(dtype=wp.vec3d),
    grid: Grid,
    y: wp.array(dtype=wp.vec3d),
    volume: wp.array(dtype=wp.float64),
    F_L_inv: wp.mat33d,
    eta: wp.float64,
    mass: wp.array3d(dtype=wp.float64),
    bound: wp.array3d(dtype=wp.float64),
    dt: wp.float64,
    forces: wp.array3d(dtype=wp.vec3d),
):
    """Kelvin-Voigt damping: Cauchy stress 2 eta_i D, D = sym(grad_x w), grad_x w = grad_y w F_L^-1;
    f_s = -sum_i w_i 2 eta_i D F_L^-T grad_y Phi_s(y_i) (material volume for spatial volume: small
    volume change). A rigid velocity field has D = 0: only deformation is damped.

    The update is explicit (w += dt M^-1 f), stable while dt lambda_max(M^-1 K) <= 2. Material
    filling whole cells has dt lambda_max = 2/3 at the cap rho h^2 / (12 eta), and every one of its
    nodes the same row bound dt R_s / m_s = 2.0, 2.5, 2.7 for 1, 2, 3 points per axis (R_s:
    Gershgorin bound of node s's row, kernel ``viscous_row_bound``). A node with a sliver of
    material in its support (the mass floor) meets nearly the full stiffness of its cells with a
    fraction of their mass: its row bound is many times a full node's, and forward Euler
    overshoots there, growing each step. So a point is damped with
    eta_i = eta min_c min(1, VISCOUS_ROW_LIMIT m_c / (dt R_c)) over its cell's corners c: no row
    exceeds about 1.5x a full node's bound (a 2x margin to instability), nodes of full cells keep
    eta, and the stress stays symmetric: forces sum to zero, momentum and angular momentum are
    exact and the damping only dissipates."""
    i = wp.tid()
    h = grid.h
    g = grid_coordinates(w, y[i], grid)
    cell = cell_of(w, g)
    t = local_coordinates(g, cell)
    share = wp.float64(1.0)
    for c in range(8):
        a = cell[0] + c // 4
        b = cell[1] + (c // 2) % 2
        d = cell[2] + c % 2
        load = dt * bound[a, b, d]
        if load > VISCOUS_ROW_LIMIT * mass[a, b, d]:
            share = wp.min(share, VISCOUS_ROW_LIMIT * mass[a, b, d] / load)
    Gx = gradient_in_cell(w, cell, t, h) * F_L_inv
    D = wp.float64(0.5) * (Gx + wp.transpose(Gx))
    stress = volume[i] * wp.float64(2.0) * eta * share * D * wp.transpose(F_L_inv)
    for c in range(8):
        wp.atomic_add(forces, cell[0] + c // 4, cell[1] + (c // 2) % 2, cell[2] + c % 2,
                      -(stress * corner_gradient(c, t, h)))
