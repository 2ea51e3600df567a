# Ref: paper eq. (1), (4)–(9), Fig. 7; SPEC.md §2 (current loop), §2.5 (DC-bus compensation)
"""Bit-true golden model of :class:`foc_servo.hdl.foc.CurrentLoop`, composed of the blocks'
models (:mod:`.clarke`, :mod:`.cordic`, :mod:`.pi`, :mod:`.svpwm`).

Everything but the two PI regulators is stateless, so it is vectorised over the samples; the
regulators step sample by sample (their state carried across calls of :meth:`CurrentLoopModel.run`,
as is the DC-bus gain, which the gateware applies one sample late). Equations: ``hdl/foc.py``.
"""

import numpy as np
from amaranth.hdl import signed

from ...hdl.fixed import Q, UQ, round_shift_np, saturate_np
from ...hdl.foc import FF_FORMAT, SPEED_WIDTH
from .clarke import clarke
from .cordic import rotate as cordic_rotate
from .rotator import rotate as table_rotate
from .pi import PIModel
from .svpwm import dcbus_apply, dcbus_gain, svpwm

__all__ = ["CurrentLoopModel", "SAMPLE_FIELDS", "CONFIG_FIELDS", "OUTPUT_FIELDS"]

#: Per-sample inputs (latched with the sample in the gateware).
SAMPLE_FIELDS = ("ia", "ib", "udc", "theta", "theta_lead", "id_ref", "iq_ref", "enable",
                 "ol_enable", "ol_ud", "ol_uq", "ff_enable", "speed")
#: Configuration inputs (stable while a sample is in flight).
CONFIG_FIELDS = ("gain_a", "gain_b", "offset_a", "offset_b", "kp_d", "kx_d", "lim_lo_d",
                 "lim_hi_d", "kp_q", "kx_q", "lim_lo_q", "lim_hi_q", "ff_l", "ff_psi",
                 "u_rated", "scale")
#: Keys of the result of :meth:`CurrentLoopModel.run`.
OUTPUT_FIELDS = ("a", "b", "c", "i_alpha", "i_beta", "i_d", "i_q", "u_d", "u_q", "u_alpha",
                 "u_beta", "duty_a", "duty_b", "duty_c", "overmod", "sat_d", "sat_q",
                 "dc_gain", "dc_limited", "udc")


class CurrentLoopModel:
    """The current loop, bit-true to :class:`foc_servo.hdl.foc.CurrentLoop` for samples that are
    all accepted (none dropped as an overrun).

    Parameters
    ----------
    width, adc_width, angle_width, rotator, iterations_per_stage, clarke_gain_format,
    kp_format, kx_format, int_guard, gain_limit
        As for :class:`~foc_servo.hdl.foc.CurrentLoop` (``iterations_per_stage`` changes timing
        only).

    Attributes
    ----------
    pi_d, pi_q : PIModel
        The regulators' state.
    dc_gain : int
        DC-bus gain (UQ2.16) the next sample will be compensated with.
    """

    def __init__(self, *, width=16, adc_width=16, angle_width=16, rotator="table",
                 iterations_per_stage=3,
                 clarke_gain_format=Q(18, 15), kp_format=UQ(16, 8), kx_format=UQ(16, 16),
                 int_guard=8, gain_limit=2.0):
        self.width = width
        self._rotate = {"table": table_rotate, "cordic": cordic_rotate}[rotator]
        self.adc_width = adc_width
        self.angle_width = angle_width
        self.clarke_gain_format = clarke_gain_format
        self.pi_d = PIModel(width=width, kp_format=kp_format, kx_format=kx_format,
                            int_guard=int_guard)
        self.pi_q = PIModel(width=width, kp_format=kp_format, kx_format=kx_format,
                            int_guard=int_guard)
        self.gain_limit_raw = round(gain_limit * (1 << 16))
        self.dc_gain = 1 << 16

    def run(self, **inputs):
        """Process a sequence of samples.

        Parameters
        ----------
        **inputs
            Every name of :data:`SAMPLE_FIELDS` and :data:`CONFIG_FIELDS`: integer arrays of one
            length (or scalars, broadcast), raw values as the gateware ports take them (``udc``,
            ``ia``, ``ib`` signed codes; ``theta`` raw binary angle; ``speed`` Q1.31 raw).

        Returns
        -------
        dict of int64 arrays
            :data:`OUTPUT_FIELDS`: ``a``, ``b``, ``c`` scaled phase currents, ``i_alpha`` …
            ``u_beta`` as the status outputs, ``duty_*`` and ``overmod`` the SVPWM result,
            ``sat_d``/``sat_q`` the PI flags, ``dc_gain`` the gain applied, ``dc_limited`` the
            flag of this sample's own bus measurement, ``udc`` the code.
        """
        missing = set(SAMPLE_FIELDS + CONFIG_FIELDS) - set(inputs)
        if missing:
            raise TypeError(f"CurrentLoopModel.run needs {sorted(missing)}")
        arrays = np.broadcast_arrays(*(np.asarray(inputs[k], dtype=np.int64)
                                       for k in SAMPLE_FIELDS + CONFIG_FIELDS))
        v = dict(zip(SAMPLE_FIELDS + CONFIG_FIELDS, (np.atleast_1d(a) for a in arrays)))
        n = v["ia"].size
        w, aw = self.width, self.angle_width
        sw = signed(w)
        turn = 1 << aw
        cordic = {"width": w, "angle_width": aw}

        c = clarke(v["ia"], v["ib"], gain_a=v["gain_a"], gain_b=v["gain_b"],
                   offset_a=v["offset_a"], offset_b=v["offset_b"], width=w,
                   gain_frac=self.clarke_gain_format.frac)
        i_d, i_q = self._rotate(c["alpha"], c["beta"], (-v["theta"]) % turn, **cordic)

        run = (v["enable"] != 0) & (v["ol_enable"] == 0)
        ol = v["ol_enable"] != 0
        ff_run = run & (v["ff_enable"] != 0)

        # Decoupling feed-forward.
        n_spd = np.asarray(saturate_np(round_shift_np(v["speed"], SPEED_WIDTH - w), sw))
        wl = np.asarray(round_shift_np(v["ff_l"] * n_spd, FF_FORMAT.frac))
        emf = np.asarray(round_shift_np(v["ff_psi"] * n_spd, FF_FORMAT.frac))
        ff_d = -np.asarray(round_shift_np(wl * i_q, w - 1))
        ff_q = np.asarray(round_shift_np(wl * i_d, w - 1)) + emf

        # The regulators: sequential.
        pi_out = np.zeros((2, n), dtype=np.int64)
        pi_sat = np.zeros((2, n), dtype=np.int64)
        for k in range(n):
            for j, (pi, ax, ref, fb) in enumerate(((self.pi_d, "d", v["id_ref"], i_d),
                                                   (self.pi_q, "q", v["iq_ref"], i_q))):
                if run[k]:
                    pi_out[j, k], pi_sat[j, k] = pi.step(
                        ref[k], fb[k], v[f"kp_{ax}"][k], v[f"kx_{ax}"][k],
                        v[f"lim_lo_{ax}"][k], v[f"lim_hi_{ax}"][k])
                else:
                    pi.clear()

        u_d = np.where(ol, v["ol_ud"],
                       saturate_np(pi_out[0] + np.where(ff_run, ff_d, 0), sw))
        u_q = np.where(ol, v["ol_uq"],
                       saturate_np(pi_out[1] + np.where(ff_run, ff_q, 0), sw))
        u_alpha, u_beta = self._rotate(u_d, u_q, (v["theta"] + v["theta_lead"]) % turn, **cordic)

        # DC-bus compensation with the gain of the previous sample's bus voltage.
        gain, limited = dcbus_gain(v["u_rated"], np.maximum(v["udc"], 0),
                                   gain_limit_raw=self.gain_limit_raw)
        gain = np.asarray(gain, dtype=np.int64)
        applied = np.concatenate([[self.dc_gain], gain[:-1]]).astype(np.int64)
        self.dc_gain = int(gain[-1])
        comp_a = dcbus_apply(u_alpha, applied, out_width=w + 1)
        comp_b = dcbus_apply(u_beta, applied, out_width=w + 1)
        duties = svpwm(comp_a, comp_b, v["scale"], width=w + 1, frac=w - 1)

        return {
            "a": c["a"], "b": c["b"], "c": c["c"], "i_alpha": c["alpha"], "i_beta": c["beta"],
            "i_d": i_d, "i_q": i_q, "u_d": np.asarray(u_d, dtype=np.int64),
            "u_q": np.asarray(u_q, dtype=np.int64), "u_alpha": u_alpha, "u_beta": u_beta,
            "duty_a": duties["a"], "duty_b": duties["b"], "duty_c": duties["c"],
            "overmod": duties["overmod"], "sat_d": pi_sat[0], "sat_q": pi_sat[1],
            "dc_gain": applied, "dc_limited": np.asarray(limited, dtype=np.int64),
            "udc": v["udc"],
        }
