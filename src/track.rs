//! Track and train data of the paper (Sec. 3.1-3.2, Fig. 7): UIC60 rail on a Winkler
//! foundation under an ETR 500 coach, and the passage histories derived from it.
//!
//! The static rail deflection under a point load `Q` on a Winkler beam is
//! `w(x) = Q beta / (2 k) e^(-beta |x|) (cos beta|x| + sin beta|x|)`,
//! `beta = (k / (4 EI))^(1/4)` (Hetenyi). Deflection is positive downward (compression).
//! A train at constant speed turns `x` into time. Pure functions: no I/O, no clock.

/// UIC60 rail mass per metre, kg/m.
pub const UIC60_MASS_KG_PER_M: f64 = 60.21;
/// UIC60 bending stiffness: 210 GPa x 3038.3 cm^4, N m^2.
pub const UIC60_EI_N_M2: f64 = 210e9 * 3038.3e-8;
/// Measured static stiffness of the ERS per metre (paper Sec. 2), N/m^2.
pub const ERS_STATIC_STIFFNESS_N_PER_M2: f64 = 60e6;

/// A train of axles passing a fixed point of the track at constant speed.
#[derive(Debug, Clone, PartialEq)]
pub struct TrainPassage {
    /// Vertical load of each axle (both wheels), N; the paper's Q = 110 kN.
    pub axle_load_n: f64,
    /// Axle positions along the train, m, measured from the first axle (0 first).
    pub axle_offsets_m: Vec<f64>,
    pub speed_m_per_s: f64,
    /// Foundation modulus, N/m^2 (force per metre of rail per metre of deflection).
    pub foundation_n_per_m2: f64,
    pub rail_ei_n_m2: f64,
}

impl TrainPassage {
    /// An ETR 500 coach (paper Fig. 7): two bogies 19 m apart, 3 m wheelbase,
    /// 110 kN axle load, on UIC60 over the measured 60 MN/m^2 static foundation.
    pub fn etr500_coach(speed_m_per_s: f64) -> TrainPassage {
        TrainPassage {
            axle_load_n: 110e3,
            axle_offsets_m: vec![0.0, 3.0, 19.0, 22.0],
            speed_m_per_s,
            foundation_n_per_m2: ERS_STATIC_STIFFNESS_N_PER_M2,
            rail_ei_n_m2: UIC60_EI_N_M2,
        }
    }

    /// `beta = (k / 4EI)^(1/4)`, 1/m.
    pub fn beta_per_m(&self) -> f64 {
        (self.foundation_n_per_m2 / (4.0 * self.rail_ei_n_m2)).powf(0.25)
    }

    /// Static deflection at distance `x_m` from a single axle, m.
    pub fn single_axle_deflection_m(&self, x_m: f64) -> f64 {
        let beta = self.beta_per_m();
        let bx = beta * x_m.abs();
        self.axle_load_n * beta / (2.0 * self.foundation_n_per_m2)
            * (-bx).exp()
            * (bx.cos() + bx.sin())
    }

    /// Static deflection of the rail at position `x_m` with the first axle at `x_first_m`
    /// and the others behind it (at smaller x), m.
    pub fn deflection_at_m(&self, x_m: f64, x_first_m: f64) -> f64 {
        self.axle_offsets_m
            .iter()
            .map(|d| self.single_axle_deflection_m(x_m - (x_first_m - d)))
            .sum()
    }

    /// Deflection at a fixed track point at time `t_s`, the first axle passing it at
    /// `t_first_s` (Fig. 7b: deflection history of the elastomer under the rail).
    pub fn deflection_history_m(&self, t_s: f64, t_first_s: f64) -> f64 {
        self.deflection_at_m(0.0, self.speed_m_per_s * (t_s - t_first_s))
    }

    /// Quasi-static force per metre of elastomer at a track point, N/m:
    /// the foundation modulus times the static deflection.
    pub fn force_per_m_history(&self, t_s: f64, t_first_s: f64) -> f64 {
        self.foundation_n_per_m2 * self.deflection_history_m(t_s, t_first_s)
    }

    /// Time for the whole coach to pass with `margin_m` of track before and after, s.
    pub fn duration_s(&self, margin_m: f64) -> f64 {
        let length = self.axle_offsets_m.iter().copied().fold(0.0, f64::max);
        (length + 2.0 * margin_m) / self.speed_m_per_s
    }
}

/// Converts km/h to m/s.
pub fn kmh_to_m_per_s(speed_kmh: f64) -> f64 {
    speed_kmh / 3.6
}
