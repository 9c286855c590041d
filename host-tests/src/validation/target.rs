//! The model's accuracy targets: what `pto validate` and the closed loop judge against.

/// P2 RMS error with a working HP transducer (σ = 0.5 bar), bar.
pub const P2_RMS_BAR: f64 = 0.3;
/// P2 max error without HP transducer, from a known start, over 60 s, bar.
pub const P2_MODEL_ONLY_MAX_BAR: f64 = 2.0;
/// Model-only window, s.
pub const MODEL_ONLY_WINDOW_S: f64 = 60.0;
/// Torque RMS error, fraction of the peak torque.
pub const TORQUE_RMS_OF_PEAK: f64 = 0.05;
/// Motor speed RMS error, fraction of the RMS speed.
pub const MOTOR_RMS_REL: f64 = 0.03;
/// Fixed point vs f64, bar, in runs whose P2 stays out of the capacitance table's cell at
/// the HP precharge.
pub const FIXED_VS_F64_BAR: f64 = 0.05;
/// Fixed point vs f64, bar, in runs that cross that cell (the depth below the precharge
/// grows exponentially there: trajectories that enter it a few LSBs apart separate).
pub const FIXED_VS_F64_CELL_BAR: f64 = 0.2;
/// The model-only 2 bar target applies to runs whose estimate stays this far above the HP
/// precharge, bar.
pub const PRECHARGE_MARGIN_BAR: f64 = 1.0;
/// Share of samples whose |P2 error| is within 2σ, at least.
pub const COVER_2S: f64 = 0.95;
/// Share of samples whose |P2 error| is within 3σ, at least.
pub const COVER_3S: f64 = 0.995;
/// The empty flag follows the plant's HP accumulator running empty within this, ms.
pub const EMPTY_FLAG_MS: f64 = 50.0;
/// Fixed point vs f64, N·m.
pub const FIXED_VS_F64_NM: f64 = 0.5;
/// Closed loop: P2 within ± this of the setpoint, bar.
pub const HOLD_P2_BAR: f64 = 2.0;
/// Closed loop: motor speed within ± this fraction of the setpoint.
pub const HOLD_SPEED_REL: f64 = 0.03;
