"""Motion models: odometry rot1-trans-rot2 (Geiser et al. 2023, Eq. 1), velocity and Ackermann.

Every model's noise lives on the odometry decomposition of the move. A move from pose
(x, y, theta) is a first rotation rot1, a translation trans and a second rotation rot2:

    x' = x + trans cos(theta + rot1),  y' = y + trans sin(theta + rot1),
    theta' = theta + rot1 + rot2.

Geiser et al. 2023, Eq. (1): the true move is drawn around the measured one with

    sigma_rot1  = a1 |trans| + b1 |rot1|          + c1      (Table 1 row 1)
    sigma_trans = a2 |trans| + b2 (|rot1|+|rot2|) + c2      (Table 1 row 2)
    sigma_rot2  = a3 |trans| + b3 |rot2|          + c3      (Table 1 row 3)

Degeneracy: when trans is near zero, rot1 is the angle of pose jitter (anything in [-pi, pi))
and the b2 |rot1| term explodes. Below ``params.min_translation`` rot1 is set to 0 and the
whole turn goes to rot2.

Bursts: wheel slip and commanded-velocity odometry err in bursts that a Gaussian with Eq. (1)'s
std calls impossible. With ``params.motion_outlier_probability`` eps > 0 the move noise is the
scale mixture (1 - eps) N(0, sigma^2) + eps N(0, kappa^2 sigma^2), kappa =
``motion_outlier_scale``: the sampler draws a burst with probability eps, the density is the
mixture's, and the FastSLAM 2.0 proposal uses its covariance E[s^2] sigma^2. eps = 0 (the
default) is Eq. (1) unchanged.

The velocity (v, omega, dt) and Ackermann (v_encoder, steering, dt) controls are integrated
exactly (constant rates over dt) into a relative pose, decomposed into (rot1, trans, rot2), and
the same Eq. (1) noise is applied. So all three share one sampler and one density.

Systematic error: odometry that reads every move too long or every turn too wide is wrong in
a way no zero-mean noise describes: the error adds up along the drive instead of averaging
out (Borenstein and Feng, "Measurement and correction of systematic odometry errors in mobile
robots", IEEE Transactions on Robotics and Automation, 1996). The measured move every model
uses is the reading times the gains g = ``params.odometry_gain`` = (g_t, g_r),

    u = (g_r rot1_read, g_t trans_read, g_r rot2_read),

and Eq. (1)'s noise is around u, with its std evaluated at u (``control_to_odometry``, the
one place a reading becomes a move, in the filter and, through ``host.in_float64``, in the
host code that smooths readings; ``with_gain`` alone is for code that fits or inverts the
gains). g = (1, 1) (the default) leaves every reading as it is, bit
for bit; ``calibrate_params`` fits g from the log (``odometry_gain.gain_update``).

Shapes: ``pose`` (..., 3), ``control`` (..., 3), ``odometry`` (..., 3) = (rot1, trans, rot2).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxslam.geometry import LOG_2PI, compose, relative, wrap_angle
from jaxslam.types import MOTION_MODELS, Params


def odometry_from_relative(delta, min_translation):
    """(rot1, trans, rot2) of a relative pose ``delta`` (..., 3) in the start pose's frame."""
    trans = jnp.hypot(delta[..., 0], delta[..., 1])
    moving = trans >= min_translation
    # Double where: arctan2(0, 0) is fine forward but its gradient is NaN.
    safe_x = jnp.where(moving, delta[..., 0], 1.0)
    safe_y = jnp.where(moving, delta[..., 1], 0.0)
    rot1 = jnp.where(moving, jnp.arctan2(safe_y, safe_x), 0.0)
    rot2 = wrap_angle(delta[..., 2] - rot1)
    return jnp.stack([rot1, trans, rot2], axis=-1)


def odometry_from_poses(pose_prev, pose_next, min_translation):
    """The move (rot1, trans, rot2) that takes ``pose_prev`` to ``pose_next``, both (..., 3)."""
    return odometry_from_relative(relative(pose_prev, pose_next), min_translation)


def nearest_decomposition(moves, reference):
    """The same moves (..., 3) written as the decomposition nearest ``reference`` (..., 3).

    A relative pose has two exact decompositions: (rot1, trans, rot2) and, driving
    backwards, (rot1 + pi, -trans, rot2 + pi) (``apply_odometry`` gives the same pose for
    both). ``odometry_from_poses`` always returns trans >= 0, so a true move that drifts a
    centimetre backwards while the measured move stood still or crept forwards comes out
    with rot1 and rot2 about pi away from the measured ones: an error of pi that the
    odometry never made. This returns, per move, the decomposition whose rot1 lies nearer
    the reference's (the backward one where cos(rot1 - rot1_ref) < 0), rotations wrapped.
    """
    flip = jnp.cos(moves[..., 0] - reference[..., 0]) < 0.0
    backward = jnp.stack([wrap_angle(moves[..., 0] + jnp.pi), -moves[..., 1],
                          wrap_angle(moves[..., 2] + jnp.pi)], axis=-1)
    return jnp.where(flip[..., None], backward, moves)


def apply_odometry(pose, odometry):
    """Pose (..., 3) after the move (rot1, trans, rot2) (..., 3); the header's equations."""
    rot1, trans, rot2 = odometry[..., 0], odometry[..., 1], odometry[..., 2]
    heading = pose[..., 2] + rot1
    return jnp.stack(
        [pose[..., 0] + trans * jnp.cos(heading), pose[..., 1] + trans * jnp.sin(heading),
         wrap_angle(heading + rot2)],
        axis=-1,
    )


def odometry_std(odometry, params: Params):
    """Geiser et al. 2023, Eq. (1) standard deviations (..., 3) of (rot1, trans, rot2)."""
    abs_rot1 = jnp.abs(odometry[..., 0])
    abs_trans = jnp.abs(odometry[..., 1])
    abs_rot2 = jnp.abs(odometry[..., 2])

    def linear(coeffs, abs_rot):
        return coeffs[0] * abs_trans + coeffs[1] * abs_rot + coeffs[2]

    return jnp.stack(
        [linear(params.rot1_noise, abs_rot1),
         linear(params.trans_noise, abs_rot1 + abs_rot2),
         linear(params.rot2_noise, abs_rot2)],
        axis=-1,
    )


def burst_variance_factor(params: Params):
    """E[s^2] of the burst scale mixture: (1 - eps) + eps kappa^2 (module docstring)."""
    eps = params.motion_outlier_probability
    return (1.0 - eps) + eps * params.motion_outlier_scale**2


def sample_odometry(key, odometry, params: Params):
    """Draw a true move around the measured ``odometry`` (3,) per Eq. (1). Returns (3,).

    With ``params.motion_outlier_probability`` eps > 0 the whole move's std is multiplied by
    ``motion_outlier_scale`` kappa with probability eps (a burst). The Gaussian draw uses
    ``key`` itself and the burst a key folded from it, so eps = 0 gives the plain Eq. (1)
    draw bit for bit.
    """
    noise = jax.random.normal(key, odometry.shape, odometry.dtype)
    burst = jax.random.uniform(jax.random.fold_in(key, 1), odometry.shape[:-1] + (1,),
                               odometry.dtype) < params.motion_outlier_probability
    scale = jnp.where(burst, params.motion_outlier_scale, 1.0).astype(odometry.dtype)
    sample = odometry + noise * scale * odometry_std(odometry, params)
    return sample.at[..., 0].set(wrap_angle(sample[..., 0])).at[..., 2].set(
        wrap_angle(sample[..., 2]))


def arc_delta(speed, yaw_rate, dt):
    """Relative pose (..., 3) after moving at constant speed and yaw rate for dt.

    delta = (v sin(w dt) / w, v (1 - cos(w dt)) / w, w dt), with the straight-line limit
    (v dt, 0, 0) as w -> 0 (double where keeps gradients finite).
    """
    angle = yaw_rate * dt
    turning = jnp.abs(angle) > 1e-6
    safe_rate = jnp.where(turning, yaw_rate, 1.0)
    forward = jnp.where(turning, jnp.sin(angle) / safe_rate, dt * (1.0 - angle**2 / 6.0))
    lateral = jnp.where(turning, (1.0 - jnp.cos(angle)) / safe_rate, dt * angle / 2.0)
    return jnp.stack([speed * forward, speed * lateral, angle], axis=-1)


def ackermann_rates(speed, steering, wheelbase, encoder_offset):
    """Rear-axle centre speed and yaw rate of an Ackermann vehicle, each (...,).

    The speed v is measured at a wheel offset H sideways from the centre line (Victoria Park:
    the rear-left encoder), the steering angle a is the front axle's, L the wheelbase:

        vc = v / (1 - tan(a) H / L),   omega = vc tan(a) / L.

    Args:
      speed: (...,) encoder-wheel speed v [m/s].  steering: (...,) steering angle a [rad].
      wheelbase: L [m].  encoder_offset: H [m]. All broadcastable.
    Returns:
      (centre_speed (...,) [m/s], yaw_rate (...,) [rad/s]).
    """
    tan_steer = jnp.tan(steering)
    centre_speed = speed / (1.0 - tan_steer * encoder_offset / wheelbase)
    return centre_speed, centre_speed * tan_steer / wheelbase


def ackermann_delta(control, params: Params):
    """Relative laser pose (..., 3) for an Ackermann control (v_encoder, steering, dt).

    Victoria Park kinematics (``ackermann_rates``): the rear-axle centre moves at vc with yaw
    rate omega; the pose is the laser's, offset (laser_forward, laser_left) from the rear axle,
    so delta = offset^-1 (+) arc (+) offset.
    """
    speed, steering, dt = control[..., 0], control[..., 1], control[..., 2]
    centre_speed, yaw_rate = ackermann_rates(speed, steering, params.wheelbase,
                                             params.encoder_offset)
    arc = arc_delta(centre_speed, yaw_rate, dt)
    offset = jnp.stack(jnp.broadcast_arrays(params.laser_forward, params.laser_left,
                                            jnp.zeros_like(params.laser_left)), axis=-1)
    offset = jnp.broadcast_to(offset, arc.shape)
    return compose(compose(relative(offset, jnp.zeros_like(offset)), arc), offset)


def with_gain(odometry, gain):
    """The reading ``odometry`` (..., 3) = (rot1, trans, rot2) times the gains ``gain`` (2,)
    = (g_t, g_r) (or gains (..., 2) of the same leading shape): (g_r rot1, g_t trans,
    g_r rot2) (module docstring, systematic error)."""
    gain = jnp.asarray(gain, odometry.dtype)
    factor = jnp.stack([gain[..., 1], gain[..., 0], gain[..., 1]], axis=-1)
    return odometry * jnp.broadcast_to(factor, odometry.shape)


def control_to_odometry(control, params: Params, motion_model: str):
    """The measured move (rot1, trans, rot2) (..., 3) of a control of the given model: its
    reading (the control itself for the odometry model, else the integrated move's
    decomposition) times ``params.odometry_gain`` (``with_gain``)."""
    if motion_model == "odometry":
        reading = control
    elif motion_model in ("velocity", "ackermann"):
        delta = (arc_delta(control[..., 0], control[..., 1], control[..., 2])
                 if motion_model == "velocity" else ackermann_delta(control, params))
        reading = odometry_from_relative(delta, params.min_translation)
    else:
        raise ValueError(f"motion_model={motion_model!r}; expected one of {list(MOTION_MODELS)}")
    return with_gain(reading, params.odometry_gain)


def sample_motion(key, pose, control, params: Params, motion_model: str = "odometry"):
    """Sample x_t ~ p(x_t | x_{t-1} = pose (3,), control (3,)). Returns (3,)."""
    odometry = control_to_odometry(control, params, motion_model)
    return apply_odometry(pose, sample_odometry(key, odometry, params))


def predict_pose(pose, control, params: Params, motion_model: str = "odometry"):
    """Noise-free motion prediction (..., 3)."""
    return apply_odometry(pose, control_to_odometry(control, params, motion_model))


def odometry_log_density(true_odometry, odometry, params: Params):
    """log p(true_odometry | odometry) over (rot1, trans, rot2), (...,).

    log[(1 - eps) N(d; 0, diag(sigma^2)) + eps N(d; 0, diag(kappa^2 sigma^2))], d the wrapped
    difference, sigma = ``odometry_std(odometry)`` (Eq. (1)), eps and kappa the burst
    probability and scale; for eps = 0 exactly the Eq. (1) Gaussian.
    """
    std = odometry_std(odometry, params)
    diff = true_odometry - odometry
    diff = diff.at[..., 0].set(wrap_angle(diff[..., 0])).at[..., 2].set(wrap_angle(diff[..., 2]))
    core = jnp.sum(-0.5 * (diff / std) ** 2 - jnp.log(std) - 0.5 * LOG_2PI, axis=-1)
    eps = params.motion_outlier_probability
    kappa = params.motion_outlier_scale
    wide = jnp.sum(-0.5 * (diff / (kappa * std)) ** 2 - jnp.log(kappa * std) - 0.5 * LOG_2PI,
                   axis=-1)
    log_eps = jnp.log(jnp.maximum(eps, 1e-30))
    mixed = jnp.logaddexp(jnp.log1p(-eps) + core, log_eps + wide)
    return jnp.where(eps > 0.0, mixed, core)


def motion_log_density(pose_prev, pose_next, control, params: Params,
                       motion_model: str = "odometry"):
    """log p(pose_next | pose_prev, control) as a density over the pose (x, y, theta).

    The move density of Eq. (1) divided by the Jacobian of (rot1, trans, rot2) -> pose, whose
    determinant is trans: p(x') = p(rot1, trans, rot2) / trans. The translation is clamped
    below by ``min_translation`` (the pure-turn regime, where the move density is itself a
    density over (x, y, theta) up to this constant).

    The robot of this density does not drive backwards: the true move of a pose is its
    forward decomposition (trans >= 0, ``odometry_from_poses``), so a pose a little behind a
    robot measured to stand still or creep forwards (farther than ``min_translation``) has
    rot1 and rot2 about pi from the measured ones and a log density about
    (pi / sigma_rot1)^2 / 2 + (pi / sigma_rot2)^2 / 2 lower (about 2e5 at 0.007 rad each):
    practically zero. The sampler's Gaussian translation does draw such poses, which this
    density then rejects. That is right for robots that never reverse (no MRCLAM reading has
    a negative velocity), and measured better than counting the backward decomposition too
    on MRCLAM robot 1 and simulated logs (in-sample: the choice was made on them; on robots
    2 and 5, held out, the two were level and main ahead; docs/results.md, mrclam,
    twenty-seventh session). Its cost: in a step where every particle's proposal lies behind
    (the observations pull the pose back), the filter's log evidence falls by about that
    much, and such single steps decide the log marginal likelihood of a run (MRCLAM robot 1:
    about -95,000 nats a step, a spread of about 290,000 nats over filter keys at one
    setting).

    Args:
      pose_prev, pose_next: (..., 3); control: (..., 3). Returns (...,).
    """
    odometry = control_to_odometry(control, params, motion_model)
    true_odometry = odometry_from_poses(pose_prev, pose_next, params.min_translation)
    jacobian = jnp.maximum(true_odometry[..., 1], params.min_translation)
    return odometry_log_density(true_odometry, odometry, params) - jnp.log(jacobian)
