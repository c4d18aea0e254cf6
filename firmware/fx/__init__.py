"""The ECU's fixed-point control path: ADC counts -> scaled signals -> state estimate ->
controller -> PWM duty counts, in integer arithmetic only (``firmware.fixedpoint``).
``c/ecu_fx.c`` is the same code in C99, using only the generated tables (``make tables``);
``tests/test_c_parity.py`` feeds it the trace the ECU records on this path and requires
identical integers on every tick. ``firmware.fx.path`` (compiled) and C, function for
function:

| ``firmware.fx.path`` | C |
|---|---|
| ``init`` | ``fx_init`` |
| ``adc_signal``, ``bump_force``, ``measure``, ``correct`` | ``adc_signal``, ``bump_force``, ``fx_measure``, ``fx_correct`` |
| ``tanh_q``, ``learn_layer``, ``bppid_step`` | ``tanh_q``, ``learn_layer``, ``bppid_step`` |
| ``pid_step`` | ``pid_step`` |
| ``lqr_force`` | ``dot_state``, ``lqr_force`` |
| ``force_of`` (skyhook, regen inline) | ``force_of``, ``skyhook_force``, ``regen_force`` |
| ``control`` | ``fx_control`` |
| ``estimate.estimate`` (the float half) | ``akf_cov_step``, ``fx_tick_cov`` (``c/akf_cov.c``) |
| ``current_reference``, ``actuator_step``, ``actuator_reset`` | ``current_reference``, ``actuator_step``, ``actuator_reset`` |

One ECU tick on this path (``firmware.ecu.Ecu(params, tables)``):

  1. ``measure``  counts -> Q signals; measured force; x_pred = Phi x + Gamma u;
                  residual z - H x_pred - D u                                      (integer)
  2. the adaptive part of the Kalman filter in float (``firmware.fx.estimate``; C:
     ``c/akf_cov.c``, ``akf_cov_step``): from the residual it adapts R-hat, computes P and
     the gain K (``firmware.kernels.akf.gain_ws``), handed over as Q numbers
     (``quantize_gain``), as a background task hands its result to the control interrupt
  3. ``correct``  x += K (residual - r)                                            (integer)
  4. road grade, road-holding check and mode logic in float, from x               (supervisor)
  5. ``control``  controller of the selected mode, crossfade, force limit, the gate,
                  force -> current -> voltage -> duty, regen bounds                (integer)

The ECU records each tick's hand-over and integers (``Ecu(..., record=True)``: ``state.TickIn``
and the outputs C compares). Formats and constants: ``fx.tables``; the tables are built
offline by ``calib.fx_tables``.
"""
