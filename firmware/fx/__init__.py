"""The ECU's fixed-point control path: ADC counts -> scaled signals -> state estimate ->
controller -> PWM duty counts, in integer arithmetic only (``firmware.fixedpoint``).
``c/ecu_fx.c`` is the same code in C99, using only the generated tables (``make tables``);
``tests/test_c_parity.py`` feeds both a recorded trace and requires identical integers on
every tick. Python and C, function for function:

| Python | C |
|---|---|
| ``fx.state.init`` | ``fx_init`` |
| ``fx.akf.adc_signal``, ``measure``, ``correct`` | ``adc_signal``, ``fx_measure``, ``fx_correct`` |
| ``control.fx.bppid.tanh_q``, ``learn_layer``, ``bppid_step`` | ``tanh_q``, ``learn_layer``, ``bppid_step`` |
| ``control.fx.pid.pid_step`` | ``pid_step`` |
| ``control.fx.lqr.dot_state``, ``force`` | ``dot_state``, ``lqr_force`` |
| ``control.fx.skyhook.force``, ``control.fx.regen.force`` | ``skyhook_force``, ``regen_force`` |
| ``control.fx.force_of``, ``control``, ``tick`` | ``force_of``, ``fx_control``, ``fx_tick`` |
| ``fx.actuator.current_reference``, ``step``, ``reset`` | ``current_reference``, ``actuator_step``, ``actuator_reset`` |

One ECU tick on this path (``firmware.ecu.init(params, fixed_point=True)``, the path object
``firmware.path.FixedPath``):

  1. ``fx.akf.measure``  counts -> Q signals; measured force; x_pred = Phi x + Gamma u;
                         residual z - H x_pred - D u                               (integer)
  2. the adaptive part of the Kalman filter in float: from the residual it adapts R-hat,
     computes P and the gain K (``firmware.akf.gain``), handed over as Q numbers
     (``fx.akf.quantize_gain``), as a background task hands its result to the control interrupt
  3. ``fx.akf.correct``  x += K (residual - r)                                     (integer)
  4. road grade, road-holding check and mode logic in float, from x               (supervisor)
  5. ``control.fx.control`` controller of the selected mode, crossfade, force limit, the gate,
                         force -> current -> voltage -> duty, regen bounds        (integer)

Formats and constants: ``fx.tables``; the tables are built offline by ``calib.fx_tables``.
"""
