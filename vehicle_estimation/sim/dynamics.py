"""Vehicle dynamics, powertrain and driver, integrated with a fixed step (semi-implicit Euler).

Model
-----
* Planar 4-wheel model of paper 004 Eqs. 1-9: vertical load transfer (Eq. 5), slip angles
  (Eq. 6), wheel forward speeds (Eq. 7), Dugoff tyres (Eq. 9), forces/moment (Eqs. 2-4).
  Longitudinal tyre forces come from the wheel torques (drive split by ``driven_axle``,
  brake torque per wheel, rolling resistance C_r F_z); the wheel slip is the quasi-static
  Dugoff slip that produces that force, sigma = F_x / (C_sigma - F_x), which also couples
  into the lateral Dugoff force through f(lambda) and 1/(1+sigma). Wheel speeds
  omega = v_t (1 + sigma) / R_t (Eq. 8).
* Longitudinal inertia of paper 003 Eq. 1: (m + I_w/r^2 + I_e G^2) dv/dt (I_e term only with
  the clutch closed). Aero drag 1/2 rho C_d A (v_x - wind_along)|.|, grade m g sin(theta),
  rolling resistance m g C_r cos(theta) (sum of C_r F_z).
* Powertrain: full-load torque curve (from max torque, max power, idle and max speed),
  throttle -> torque, engine drag, automatic gearbox (up/down-shift on engine speed with a
  throttle-dependent schedule, torque interruption during shifts), launch clutch that
  slips below the gear-1 idle speed, final drive, ``driveline_efficiency`` (applied to
  positive and negative torque, as paper 004 Eq. 28 does).
* Below 1 m/s the lateral states follow the kinematic bicycle model (the slip-angle model
  is singular at v_x -> 0). At rest the brakes hold the car (no creep, no rolling back).
* Driver at 100 Hz: speed PI + feed-forward (acceleration of the reference and a
  resistance model) -> throttle/brake; pure pursuit on the road path -> steering.
"""

from __future__ import annotations

import math

import numpy as np

from vehicle_estimation.contract.vehicle import VehicleParams


# ----------------------------------------------------------------------------- engine map
def _dugoff_lateral(cornering_stiffness: float, tan_alpha: float, sg: float, mu_fz: float,
                    slip_stiffness: float) -> float:
    """Dugoff lateral tyre force (paper 004 Eq. 9) of one wheel, scalar, for the 500 Hz loop.

    ``sg`` is the slip term Fx / (Cs - Fx) the loop derives from the longitudinal force,
    ``mu_fz`` the friction limit mu·Fz of the wheel."""
    force = cornering_stiffness * tan_alpha / (1 + sg)
    den = 2.0 * math.sqrt((slip_stiffness * sg) ** 2 + (cornering_stiffness * tan_alpha) ** 2)
    if den > 0:
        lam = mu_fz * (1 + sg) / den
        if lam < 1.0:
            force *= (2.0 - lam) * lam
    return force


def full_load_torque(vp: VehicleParams, w: float) -> float:
    """Full-load (wide-open throttle) brake torque before friction [N m] at engine speed w."""
    wi, wm, t0 = vp.engine_idle_speed, vp.engine_max_speed, vp.engine_max_torque
    wp = min(vp.engine_max_power / t0, 0.95 * wm)
    wt = wi + 0.35 * (wp - wi)
    if w < wt:
        return t0 * (0.65 + 0.35 * max(0.0, (w - wi)) / (wt - wi))
    if w <= wp:
        return t0
    if w <= wm:
        return vp.engine_max_power / w
    return max(0.0, vp.engine_max_power / wm * (1.0 - (w - wm) / (0.05 * wm)))


def engine_drag(vp: VehicleParams, w: float) -> float:
    """Friction + pumping torque at closed throttle [N m]."""
    return vp.engine_drag_torque * (0.6 + 0.4 * w / vp.engine_max_speed)


def simulate_dynamics(vp: VehicleParams, road, v_ref: np.ndarray, duration_s: float,
                      initial_speed: float, wind_enu, physics_rate: float = 500.0,
                      control_rate: float = 100.0) -> dict:
    """Run the closed loop. Returns ``fast`` arrays (physics rate) and ``slow`` (control rate)."""
    dt = 1.0 / physics_rate
    sub = int(round(physics_rate / control_rate))
    if abs(sub * control_rate - physics_rate) > 1e-9:
        raise ValueError("physics_rate must be an integer multiple of the control rate")
    dtc = 1.0 / control_rate
    n_ctrl = int(math.floor(duration_s * control_rate + 1e-9)) + 1
    n_fast = n_ctrl * sub

    # ---- parameters as locals (speed)
    m = vp.mass
    g = vp.gravity
    lf, lr = vp.lf, vp.lr
    L = lf + lr
    bF, bR = vp.track_front, vp.track_rear
    h = vp.cg_height
    Iz = vp.yaw_inertia
    R = vp.wheel_radius
    Cs = vp.longitudinal_stiffness
    Caf, Car = vp.cornering_stiffness_front, vp.cornering_stiffness_rear
    mu = vp.road_friction
    Cr = vp.rolling_resistance
    kaero = 0.5 * vp.air_density * vp.drag_coefficient * vp.frontal_area
    eta = vp.driveline_efficiency
    Jw = vp.wheel_inertia / R ** 2
    Ie = vp.engine_inertia
    i0 = vp.final_drive
    ratios = vp.gear_ratios
    ngear = len(ratios)
    Gs = [gr * i0 / R for gr in ratios]
    wi, wm = vp.engine_idle_speed, vp.engine_max_speed
    Tb_max = vp.max_brake_torque
    fshare = vp.brake_front_share
    if vp.driven_axle == "front":
        dsplit = (0.5, 0.5, 0.0, 0.0)
    elif vp.driven_axle == "rear":
        dsplit = (0.0, 0.0, 0.5, 0.5)
    else:
        dsplit = (0.25, 0.25, 0.25, 0.25)
    d1, d2, d3, d4 = dsplit
    bshare = (fshare / 2, fshare / 2, (1 - fshare) / 2, (1 - fshare) / 2)
    Fz_static_f = m * lr * g / (2 * L)
    Fz_static_r = m * lf * g / (2 * L)
    delta_max = 0.55
    steer_tau = 0.08
    steer_rate = 0.6  # road-wheel rad/s
    v_kin = 1.0
    shift_time = 0.25 if m < 5000 else 0.6
    min_shift_interval = 1.0
    wE, wN = float(wind_enu[0]), float(wind_enu[1])
    m_eff_nom = m + Jw

    # ---- road arrays
    rs, rx, ry, rpsi, rz_grade = road.s, road.x, road.y, road.psi, road.grade
    n_road = rs.size
    ds = float(rs[1] - rs[0])
    closed = road.closed
    road_len = n_road * ds if closed else float(rs[-1])
    v_of_s = road.v_of_s
    distance_mode = v_of_s is not None and np.all(np.isnan(v_ref))
    rx_l, ry_l, rpsi_l = rx.tolist(), ry.tolist(), rpsi.tolist()
    grade_l = np.arctan(rz_grade).tolist()
    vofs_l = v_of_s.tolist() if v_of_s is not None else None

    def road_index(s: float) -> int:
        i = int(s / ds + 0.5)
        if closed:
            return i % n_road
        return min(max(i, 0), n_road - 1)

    # reference feed-forward acceleration (time-based profiles)
    vr = np.asarray(v_ref, dtype=float)
    if vr.size < n_ctrl + 200:
        vr = np.concatenate([vr, np.full(n_ctrl + 200 - vr.size, vr[-1])])
    vr_f = np.nan_to_num(vr, nan=0.0)
    # preview 0.3 s, feed-forward acceleration from a 1 s central difference
    npv = int(round(0.3 * control_rate))
    nd = int(round(0.5 * control_rate))
    idx = np.arange(vr.size)
    a_ff_arr = (vr_f[np.minimum(idx + nd + npv, vr.size - 1)] - vr_f[np.maximum(idx - nd + npv, 0)]) / (2 * nd * dtc)
    vr_l = vr.tolist()
    aff_l = a_ff_arr.tolist()

    # ---- state
    X = Y = Z = 0.0
    psi = float(rpsi[0])
    vx = float(initial_speed)
    vy = 0.0
    r = 0.0
    delta = 0.0
    s_path = 0.0
    i_path = 0
    integ = 0.0
    ax_f = 0.0   # filtered accelerations for load transfer
    ay_f = 0.0
    # gear at start
    gear = 1
    if vx > 0:
        for gg in range(ngear, 0, -1):
            if vx * Gs[gg - 1] > wi + 0.25 * (wm - wi):
                gear = gg
                break
    t_since_shift = 10.0
    shift_left = 0.0
    w_e = wi
    Te = 0.0
    load = 0.0
    throttle = 0.0
    F_drive = 0.0
    Tb1 = Tb2 = Tb3 = Tb4 = 0.0
    clutch = vx > 0
    J = Jw + (Ie * Gs[gear - 1] ** 2 if clutch else 0.0)
    theta = grade_l[0]
    Tb_hold = 4 * 0.3 * Tb_max if vx <= 0.0 else 0.0

    # ---- output buffers
    F = {k: [0.0] * n_fast for k in ("vx", "vy", "r", "ax", "ay", "vxd", "vyd", "X", "Y", "Z", "psi", "theta")}
    fvx, fvy, fr, fax, fay, fvxd, fvyd = F["vx"], F["vy"], F["r"], F["ax"], F["ay"], F["vxd"], F["vyd"]
    fX, fY, fZ, fpsi, fth = F["X"], F["Y"], F["Z"], F["psi"], F["theta"]
    S = {k: [0.0] * n_ctrl for k in ("delta", "w_e", "Te", "load", "throttle", "gear", "F_drive",
                                     "Tb1", "Tb2", "Tb3", "Tb4", "w1", "w2", "w3", "w4", "v_ref",
                                     "s", "lat_err", "Fz1", "Fz2", "Fz3", "Fz4", "clutch")}
    sdelta, swe, sTe, sload, sthr, sgear, sFd = (S[k] for k in ("delta", "w_e", "Te", "load", "throttle", "gear", "F_drive"))
    sTb = [S["Tb1"], S["Tb2"], S["Tb3"], S["Tb4"]]
    sw = [S["w1"], S["w2"], S["w3"], S["w4"]]
    sFz = [S["Fz1"], S["Fz2"], S["Fz3"], S["Fz4"]]
    svref, ss, slat, sclutch = S["v_ref"], S["s"], S["lat_err"], S["clutch"]

    sin, cos, atan2, atan, tan = math.sin, math.cos, math.atan2, math.atan, math.tan
    w1 = w2 = w3 = w4 = 0.0
    Fz1 = Fz2 = Fz_static_f
    Fz3 = Fz4 = Fz_static_r
    kf = 0.0

    for k in range(n_ctrl):
        # ================= driver / powertrain at control rate
        # path progress: project on the local tangent (two iterations)
        for _ in range(2):
            i_path = road_index(s_path)
            cp, sp_ = cos(rpsi_l[i_path]), sin(rpsi_l[i_path])
            dxp, dyp = X - rx_l[i_path], Y - ry_l[i_path]
            s_path = i_path * ds + dxp * cp + dyp * sp_
            if closed:
                s_path %= road_len
        i_path = road_index(s_path)
        lat_err = -(X - rx_l[i_path]) * sin(rpsi_l[i_path]) + (Y - ry_l[i_path]) * cos(rpsi_l[i_path])
        theta = grade_l[i_path]
        sth, cth = sin(theta), cos(theta)

        # steering: pure pursuit
        Ld = max(6.0, 1.1 * vx)
        j = road_index(s_path + Ld)
        tx, ty = rx_l[j] - X, ry_l[j] - Y
        alpha = atan2(ty, tx) - psi
        alpha = (alpha + math.pi) % (2 * math.pi) - math.pi
        kap_cmd = 2.0 * sin(alpha) / max(math.hypot(tx, ty), 1.0)
        # pure pursuit + yaw-rate feedback (damps weaving, needed for oversteering vehicles)
        d_cmd = atan(L * kap_cmd) + 1.5 * L * (vx * kap_cmd - r) / max(vx, 5.0)
        d_cmd = max(-delta_max, min(delta_max, d_cmd))

        # speed reference
        if distance_mode:
            jv = road_index(s_path + vx * 0.8)
            v_target = vofs_l[jv]
            jv2 = road_index(s_path + vx * 0.8 + 10.0)
            a_ff = (vofs_l[jv2] - v_target) / 10.0 * max(vx, 1.0)
        else:
            v_target = vr_l[k]
            a_ff = aff_l[k]
        coast = v_target != v_target  # NaN
        v_cmd = v_target
        if not coast and k + npv < len(vr_l) and not distance_mode:
            v_cmd = vr_l[k + npv]
            if v_cmd != v_cmd:
                v_cmd = v_target

        t_since_shift += dtc
        Tb_total = 0.0
        if coast or (v_cmd < 0.05 and v_target < 0.05 and vx < 0.3):
            # coast: neutral, no brake. stop/hold: brakes, clutch open, first gear
            throttle = 0.0
            clutch = False
            F_drive = 0.0
            Te = 0.0
            w_e = wi
            integ = 0.0
            shift_left = 0.0
            if not coast:
                # ramp the brake from its current level to the hold torque (no stop jerk)
                Tb_hold = min(Tb_hold + 4 * 0.3 * Tb_max * dtc, 4 * 0.3 * Tb_max)
                Tb_total = Tb_hold
                gear = 1
            else:
                for gg in range(ngear, 0, -1):   # keep a sensible gear for re-engagement
                    if vx * Gs[gg - 1] > wi * 1.3 or gg == 1:
                        gear = gg
                        break
            load = engine_drag(vp, w_e) / full_load_torque(vp, w_e)
        else:
            e = v_cmd - vx
            a_des = a_ff + 0.8 * e + 0.15 * integ
            F_res = kaero * vx * vx + Cr * m * g * cth + m * g * sth
            F_req = m_eff_nom * a_des + F_res
            # ---- gearbox: schedule on engine speed
            w_g = vx * Gs[gear - 1]
            thr_est = min(1.0, max(0.0, throttle))
            w_up = wi + (0.30 + 0.45 * thr_est) * (wm - wi)
            w_dn = wi + (0.06 + 0.25 * thr_est) * (wm - wi)
            if shift_left <= 0.0 and (t_since_shift > min_shift_interval or w_g > 0.97 * wm):
                if gear < ngear and w_g > w_up and vx * Gs[gear] > 1.1 * w_dn:
                    # up-shift, skipping gears (at most 3) while the engine stays well above w_dn
                    g_new = gear + 1
                    while (g_new < ngear and g_new < gear + 3
                           and vx * Gs[g_new] > max(1.3 * w_dn, wi + 0.3 * (w_up - wi))):
                        g_new += 1
                    gear = g_new
                    t_since_shift = 0.0
                    shift_left = shift_time
                elif gear > 1 and w_g < w_dn:
                    gear -= 1
                    t_since_shift = 0.0
                    shift_left = shift_time
                elif gear > 1 and thr_est > 0.95 and vx * Gs[gear - 2] < 0.8 * w_up:
                    gear -= 1  # kick-down
                    t_since_shift = 0.0
                    shift_left = shift_time
            G = Gs[gear - 1]
            w_in = vx * G
            slipping = w_in < wi * 1.02
            if slipping and gear > 1 and shift_left <= 0.0:
                gear = 1
                G = Gs[0]
                w_in = vx * G
                slipping = w_in < wi * 1.02
            if shift_left > 0.0:
                # torque interruption while shifting
                shift_left -= dtc
                clutch = False
                F_drive = 0.0
                Te = 0.0
                w_e = max(wi, w_in)
                throttle = min(1.0, engine_drag(vp, w_e) / max(full_load_torque(vp, w_e), 1.0))
                load = throttle
            else:
                w_e = max(w_in, wi * (1.0 + 0.6 * thr_est)) if slipping else w_in
                Tmax = max(full_load_torque(vp, w_e), 1.0)
                Tdrag = engine_drag(vp, w_e)
                Te_req = F_req / (G * eta)
                sat = False
                if Te_req > -Tdrag or slipping:
                    throttle = (Te_req + Tdrag) / Tmax
                    if throttle >= 1.0:
                        throttle = 1.0
                        sat = e > 0
                    elif throttle <= 0.0:
                        throttle = 0.0
                        sat = e < 0
                    Te = throttle * Tmax - Tdrag
                    if slipping and Te < 0.0:
                        Te = 0.0
                        throttle = Tdrag / Tmax
                else:
                    throttle = 0.0
                    Te = -Tdrag
                    Tb_total = (Te * G * eta - F_req) * R
                F_drive = Te * G * eta
                clutch = not slipping
                if slipping and Te <= 0.0:
                    w_e = wi
                if slipping and F_req < F_drive:
                    # launch clutch open/slipping: decelerate with the brakes only
                    Tb_total = (F_drive - F_req) * R
                load = min(1.0, max(0.0, (Te + Tdrag) / Tmax))
                if not sat:
                    integ += e * dtc
            if Tb_total > 4 * Tb_max:
                Tb_total = 4 * Tb_max
            Tb_hold = Tb_total
        J = Jw + (Ie * Gs[gear - 1] ** 2 if clutch else 0.0)
        Tb1 = min(Tb_total * bshare[0], Tb_max)
        Tb2 = min(Tb_total * bshare[1], Tb_max)
        Tb3 = min(Tb_total * bshare[2], Tb_max)
        Tb4 = min(Tb_total * bshare[3], Tb_max)
        Fd1, Fd2, Fd3, Fd4 = F_drive * d1, F_drive * d2, F_drive * d3, F_drive * d4
        Fbrake = (Tb1 + Tb2 + Tb3 + Tb4) / R
        meff = m + J
        w_along = wE * cos(psi) + wN * sin(psi)

        # record control-rate signals (state at t_k)
        sdelta[k], swe[k], sTe[k], sload[k], sthr[k], sgear[k], sFd[k] = delta, w_e, Te, load, throttle, gear, F_drive
        sTb[0][k], sTb[1][k], sTb[2][k], sTb[3][k] = Tb1, Tb2, Tb3, Tb4
        svref[k] = v_target if not coast else float("nan")
        ss[k] = s_path
        slat[k] = lat_err
        sclutch[k] = 1.0 if clutch else 0.0

        # ================= physics sub-steps
        for jj in range(sub):
            kf = k * sub + jj
            # steering actuator
            dd = (d_cmd - delta) / steer_tau * dt
            lim = steer_rate * dt
            delta += max(-lim, min(lim, dd))
            cd, sd = cos(delta), sin(delta)
            # vertical loads (Eq. 5) with filtered accelerations
            tf = m * h * ax_f / (2 * L)
            latf = m * h * lr * ay_f / (L * bF)
            latr = m * h * lf * ay_f / (L * bR)
            Fz1 = Fz_static_f * cth - tf - latf
            Fz2 = Fz_static_f * cth - tf + latf
            Fz3 = Fz_static_r * cth + tf - latr
            Fz4 = Fz_static_r * cth + tf + latr
            if Fz1 < 50.0: Fz1 = 50.0
            if Fz2 < 50.0: Fz2 = 50.0
            if Fz3 < 50.0: Fz3 = 50.0
            if Fz4 < 50.0: Fz4 = 50.0
            va = vx - w_along
            F_aero = kaero * va * abs(va)
            F_grav = m * g * sth
            if vx <= 1e-6:
                # ---- at rest: static friction of the brakes (and tyres) holds the car
                F_push = F_drive - F_grav - F_aero
                F_hold = Fbrake + 0.5 * Cr * m * g * cth
                if F_push <= F_hold:
                    vx = 0.0
                    vy = 0.0
                    r = 0.0
                    vxd = 0.0
                    ax_k = 0.0
                    ay_k = 0.0
                    vyd = 0.0
                    w1 = w2 = w3 = w4 = 0.0
                else:
                    vxd = (F_push - F_hold) / meff
                    vx = vxd * dt
                    ax_k = vxd
                    ay_k = 0.0
                    vyd = 0.0
                    vy = vx * lr * tan(delta) / L
                    r = vx * tan(delta) / L
                    w1 = w2 = w3 = w4 = vx / R
            else:
                # ---- longitudinal wheel forces from torques
                rr1, rr2, rr3, rr4 = Cr * Fz1, Cr * Fz2, Cr * Fz3, Cr * Fz4
                Fx1 = Fd1 - Tb1 / R - rr1
                Fx2 = Fd2 - Tb2 / R - rr2
                Fx3 = Fd3 - Tb3 / R - rr3
                Fx4 = Fd4 - Tb4 / R - rr4
                lim1, lim2, lim3, lim4 = mu * Fz1, mu * Fz2, mu * Fz3, mu * Fz4
                if Fx1 > lim1: Fx1 = lim1
                elif Fx1 < -lim1: Fx1 = -lim1
                if Fx2 > lim2: Fx2 = lim2
                elif Fx2 < -lim2: Fx2 = -lim2
                if Fx3 > lim3: Fx3 = lim3
                elif Fx3 < -lim3: Fx3 = -lim3
                if Fx4 > lim4: Fx4 = lim4
                elif Fx4 < -lim4: Fx4 = -lim4
                sg1 = Fx1 / (Cs - Fx1)
                sg2 = Fx2 / (Cs - Fx2)
                sg3 = Fx3 / (Cs - Fx3)
                sg4 = Fx4 / (Cs - Fx4)
                hbf = 0.5 * bF * r
                hbr = 0.5 * bR * r
                if vx >= v_kin:
                    # ---- slip angles (Eq. 6) and Dugoff lateral forces (Eq. 9)
                    vfy = vy + lf * r
                    vry = -vy + lr * r
                    ta1 = tan(delta - atan2(vfy, vx - hbf))
                    ta2 = tan(delta - atan2(vfy, vx + hbf))
                    ta3 = tan(atan2(vry, vx - hbr))
                    ta4 = tan(atan2(vry, vx + hbr))
                    Fy1 = _dugoff_lateral(Caf, ta1, sg1, mu * Fz1, Cs)
                    Fy2 = _dugoff_lateral(Caf, ta2, sg2, mu * Fz2, Cs)
                    Fy3 = _dugoff_lateral(Car, ta3, sg3, mu * Fz3, Cs)
                    Fy4 = _dugoff_lateral(Car, ta4, sg4, mu * Fz4, Cs)
                    Fxf = Fx1 + Fx2
                    Fyf = Fy1 + Fy2
                    FX = Fxf * cd + Fx3 + Fx4 - Fyf * sd
                    FY = Fxf * sd + Fy3 + Fy4 + Fyf * cd
                    Mz = (lf * Fxf * sd - lr * (Fy3 + Fy4) + lf * Fyf * cd
                          - 0.5 * bF * (Fx1 - Fx2) * cd + 0.5 * bF * (Fy1 - Fy2) * sd
                          - 0.5 * bR * (Fx3 - Fx4))
                    vxd = (FX - F_aero - F_grav + m * r * vy) / meff
                    vyd = FY / m - r * vx
                    rd = Mz / Iz
                    vx_new = vx + vxd * dt
                    vy += vyd * dt
                    r += rd * dt
                    ax_k = vxd - r * vy
                    ay_k = vyd + r * vx
                    vx = vx_new if vx_new > 0.0 else 0.0
                else:
                    # ---- kinematic bicycle at very low speed
                    FX = Fx1 + Fx2 + Fx3 + Fx4
                    vxd = (FX - F_aero - F_grav) / meff
                    vx_new = vx + vxd * dt
                    if vx_new < 0.0:
                        vx_new = 0.0
                        vxd = -vx / dt
                    td = tan(delta)
                    vy_new = vx_new * lr * td / L
                    r_new = vx_new * td / L
                    vyd = (vy_new - vy) / dt
                    vx, vy, r = vx_new, vy_new, r_new
                    ax_k = vxd - r * vy
                    ay_k = vyd + r * vx
                # wheel speeds (Eqs. 7-8)
                vt1 = (vx - hbf) * cd + (vy + lf * r) * sd
                vt2 = (vx + hbf) * cd + (vy + lf * r) * sd
                w1 = vt1 * (1 + sg1) / R
                w2 = vt2 * (1 + sg2) / R
                w3 = (vx - hbr) * (1 + sg3) / R
                w4 = (vx + hbr) * (1 + sg4) / R
                if vx <= 0.0:
                    w1 = w2 = w3 = w4 = 0.0
            # load-transfer accelerations: low-pass (~15 Hz) to avoid an algebraic loop
            ax_f += 0.17 * (ax_k - ax_f)
            ay_f += 0.17 * (ay_k - ay_f)
            # record the state at the start of the step... (after update = end of step)
            # kinematics (semi-implicit: new velocities)
            cps, sps = cos(psi), sin(psi)
            fvxd[kf], fvyd[kf], fax[kf], fay[kf] = vxd, vyd, ax_k, ay_k
            X += (vx * cps * cth - vy * sps) * dt
            Y += (vx * sps * cth + vy * cps) * dt
            Z += vx * sth * dt
            psi += r * dt
            fvx[kf], fvy[kf], fr[kf] = vx, vy, r
            fX[kf], fY[kf], fZ[kf], fpsi[kf], fth[kf] = X, Y, Z, psi, theta
        sw[0][k], sw[1][k], sw[2][k], sw[3][k] = w1, w2, w3, w4
        sFz[0][k], sFz[1][k], sFz[2][k], sFz[3][k] = Fz1, Fz2, Fz3, Fz4

    fast = {k: np.asarray(v) for k, v in F.items()}
    slow = {k: np.asarray(v) for k, v in S.items()}
    # fast arrays hold the state at the END of each step: t = (i+1)*dt
    fast["t"] = (np.arange(n_fast) + 1) * dt
    slow["t"] = np.arange(n_ctrl) * dtc
    return {"fast": fast, "slow": slow, "dt": dt, "sub": sub}
