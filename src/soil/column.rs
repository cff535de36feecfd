//! The discretised soil column of MODEL.md §1: fluxes, sinks and their
//! derivatives as functions of the cell heads.
//!
//! With `w_i = θ(h_i) + Ss·h_i` the stored water of cell i, the column obeys
//!
//! ```text
//! dw_i/dt = (q_i − q_{i+1})/dz − S_i          (mass balance of cell i)
//! dI/dt = q_0,  dD/dt = q_n,  dU/dt = Σ S_i·dz,  dR/dt = I + P − q_0
//! ```
//!
//! for the cumulative infiltration I, drainage D, uptake U and runoff R. This is
//! the cell equation `(C + Ss)·dh/dt = …` of MODEL.md in the "mixed form" of
//! Celia et al. (1990): written for the stored water, `Σ w_i·dz − I + D + U` is
//! constant for any heads, which the integrators turn into an exact water balance.

// Index loops over cells and stages read like the equations they implement.
#![allow(clippy::needless_range_loop)]

use super::hydraulics::{HydraulicState, VanGenuchten};
use super::uptake::Crop;

/// Water supplied and demanded over one sampling step, in m/s, all held constant.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Forcing {
    /// Irrigation rate u [m/s].
    pub irrigation: f64,
    /// Reference evapotranspiration ET0 [m/s].
    pub reference_et: f64,
    /// Precipitation P [m/s].
    pub precipitation: f64,
}

impl Forcing {
    /// Every rate must be finite and non-negative.
    pub fn validate(&self) -> Result<(), String> {
        for (name, v) in [
            ("irrigation", self.irrigation),
            ("reference evapotranspiration", self.reference_et),
            ("precipitation", self.precipitation),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(format!("{name} rate must be finite and >= 0, got {v}"));
            }
        }
        Ok(())
    }
}

/// Geometry and materials of a column.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Column {
    soil: VanGenuchten,
    crop: Crop,
    depth: f64,
    cells: usize,
}

/// Whether [`Column::evaluate`] computes derivatives with respect to the heads.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Derivatives {
    Included,
    Omitted,
}

/// Rates at a set of heads, and (optionally) their derivatives: a workspace that
/// [`Column::evaluate`] fills, allocated once per column.
#[derive(Debug, Clone)]
pub struct Evaluation {
    /// Hydraulic state of every cell.
    pub states: Vec<HydraulicState>,
    /// dw_i/dt of every cell [1/s].
    pub storage: Vec<f64>,
    /// Rates of the water amounts [m/s]: infiltration, drainage, uptake, runoff.
    pub amounts: [f64; AMOUNTS],
    /// d(dw_i/dt)/dh_{i−1} (entry 0 unused).
    pub lower: Vec<f64>,
    /// d(dw_i/dt)/dh_i.
    pub diagonal: Vec<f64>,
    /// d(dw_i/dt)/dh_{i+1} (last entry unused).
    pub upper: Vec<f64>,
    /// d(infiltration rate)/dh_0 (the runoff rate has the opposite sign).
    pub top_gradient: f64,
    /// d(drainage rate)/dh_{n−1}.
    pub bottom_gradient: f64,
    /// d(uptake rate)/dh_i.
    pub uptake_gradient: Vec<f64>,
    /// (dK_i/du_i, dh_i/du_i) the derivatives were taken with ((K', 1) for u = h).
    pub(super) chains: Vec<(f64, f64)>,
    /// Cells evaluated on the saturated branch whatever their head (θ = θs,
    /// K = Ks, C = K' = 0): the integrator's active-set iteration sets them.
    pub(super) saturated_branch: Vec<bool>,
}

impl Evaluation {
    pub fn new(cells: usize) -> Self {
        let zeros = vec![0.0; cells];
        Evaluation {
            states: vec![VanGenuchten::SANDY_LOAM.state(0.0); cells],
            storage: zeros.clone(),
            amounts: [0.0; AMOUNTS],
            lower: zeros.clone(),
            diagonal: zeros.clone(),
            upper: zeros.clone(),
            top_gradient: 0.0,
            bottom_gradient: 0.0,
            uptake_gradient: zeros,
            chains: vec![(0.0, 1.0); cells],
            saturated_branch: vec![false; cells],
        }
    }
}

/// Per cell i, from (i, h_i, state_i): (dK_i/du_i, dh_i/du_i) for the unknown u_i.
pub(super) type Chain<'a> = dyn Fn(usize, f64, &HydraulicState) -> (f64, f64) + 'a;

/// Positions of the water amounts behind the cells in the state vector.
pub const INFILTRATION: usize = 0;
pub const DRAINAGE: usize = 1;
pub const UPTAKE: usize = 2;
pub const RUNOFF: usize = 3;
/// Number of water amounts after the cell storages.
pub const AMOUNTS: usize = 4;

impl Column {
    /// A column of `depth` m in `cells` equal cells.
    pub fn new(soil: VanGenuchten, crop: Crop, depth: f64, cells: usize) -> Result<Self, String> {
        soil.validate()?;
        crop.validate()?;
        if !(depth.is_finite() && depth > 0.0) {
            return Err(format!("column depth must be > 0, got {depth}"));
        }
        if cells < 2 {
            return Err(format!("a column needs at least 2 cells, got {cells}"));
        }
        if crop.rooting_depth >= depth {
            return Err(format!(
                "rooting depth {} must be shallower than the column depth {depth}",
                crop.rooting_depth
            ));
        }
        let column = Column {
            soil,
            crop,
            depth,
            cells,
        };
        if column.root_cells() == 0 {
            return Err(format!(
                "rooting depth {} is shallower than the first cell centre {}",
                crop.rooting_depth,
                column.cell_thickness() / 2.0
            ));
        }
        Ok(column)
    }

    pub fn soil(&self) -> &VanGenuchten {
        &self.soil
    }

    pub fn crop(&self) -> &Crop {
        &self.crop
    }

    pub fn depth(&self) -> f64 {
        self.depth
    }

    pub fn cells(&self) -> usize {
        self.cells
    }

    /// dz = L/n.
    pub fn cell_thickness(&self) -> f64 {
        self.depth / self.cells as f64
    }

    /// Depth of the centre of cell i, (i + ½)·dz.
    pub fn cell_centre(&self, i: usize) -> f64 {
        (i as f64 + 0.5) * self.cell_thickness()
    }

    /// Number of cells whose centre is shallower than the rooting depth.
    pub fn root_cells(&self) -> usize {
        (0..self.cells)
            .take_while(|&i| self.cell_centre(i) < self.crop.rooting_depth)
            .count()
    }

    /// The cell that holds the rooting depth: where the sensor sits.
    pub fn sensor_cell(&self) -> usize {
        ((self.crop.rooting_depth / self.cell_thickness()) as usize).min(self.cells - 1)
    }

    /// Infiltration capacity of a ponded surface into the top cell, and its
    /// derivative with respect to the top cell's unknown (dK/du = `dk`,
    /// dh/du = `dh`; with u = h these are K' and 1): `K_top·[(0 − h_0)/(dz/2) + 1]`,
    /// `K_top = (Ks + K(h_0))/2`.
    fn infiltration_capacity(&self, h: f64, s: &HydraulicState, dk: f64, dh: f64) -> (f64, f64) {
        let half = self.cell_thickness() / 2.0;
        let k_top = 0.5 * (self.soil.saturated_conductivity + s.conductivity);
        let gradient = -h / half + 1.0;
        (k_top * gradient, 0.5 * dk * gradient - k_top / half * dh)
    }

    /// Sink rate at full stress factor, Kc·ET0/z_r [1/s].
    fn potential_sink(&self, forcing: &Forcing) -> f64 {
        self.crop.crop_coefficient * forcing.reference_et / self.crop.rooting_depth
    }

    /// Rates of the stored water and of the water amounts at the given heads,
    /// with their derivatives with respect to the heads when `derivatives` is set.
    pub fn evaluate(
        &self,
        heads: &[f64],
        forcing: &Forcing,
        out: &mut Evaluation,
        derivatives: Derivatives,
    ) {
        self.evaluate_in(heads, forcing, out, derivatives, None::<&Chain>)
    }

    /// [`Column::evaluate`] with the derivatives taken with respect to other
    /// unknowns than the heads: `chain(i, h_i, state_i)` gives (dK_i/du_i,
    /// dh_i/du_i) for the unknown u_i of cell i (see the integrator's Newton
    /// coordinates near saturation). The rates are the same.
    pub(super) fn evaluate_in<C>(
        &self,
        heads: &[f64],
        forcing: &Forcing,
        out: &mut Evaluation,
        derivatives: Derivatives,
        chain: Option<&C>,
    ) where
        C: Fn(usize, f64, &HydraulicState) -> (f64, f64) + ?Sized,
    {
        let n = self.cells;
        debug_assert_eq!(heads.len(), n);
        let dz = self.cell_thickness();
        let supply = forcing.irrigation + forcing.precipitation;
        let sink = self.potential_sink(forcing);
        let roots = self.root_cells();
        let with_derivatives = derivatives == Derivatives::Included;
        for ((state, &h), &saturated) in out.states.iter_mut().zip(heads).zip(&out.saturated_branch)
        {
            *state = self.soil.state(if saturated { h.max(0.0) } else { h });
        }
        if with_derivatives {
            out.lower.fill(0.0);
            out.diagonal.fill(0.0);
            out.upper.fill(0.0);
            out.uptake_gradient.fill(0.0);
        }
        let states = &out.states;
        // (dK/du, dh/du) of every cell, only where derivatives are wanted
        let chains = &mut out.chains;
        if with_derivatives {
            for i in 0..n {
                chains[i] = match chain {
                    Some(c) => c(i, heads[i], &states[i]),
                    None => (states[i].conductivity_derivative, 1.0),
                };
            }
        }
        let chains = &out.chains;
        let dk = |i: usize| chains[i].0;
        let dh = |i: usize| chains[i].1;

        // Top face: infiltration, capped by what a ponded surface can drive in.
        let (capacity, d_capacity) = self.infiltration_capacity(heads[0], &states[0], dk(0), dh(0));
        let q0 = supply.min(capacity);
        out.amounts[INFILTRATION] = q0;
        out.amounts[RUNOFF] = supply - q0;
        out.top_gradient = if capacity < supply { d_capacity } else { 0.0 };
        let mut q_in = q0;
        if with_derivatives {
            out.diagonal[0] += out.top_gradient / dz;
        }
        let mut uptake = 0.0;
        for i in 0..n {
            let h = heads[i];
            let cur = &states[i];
            // Face below cell i: to cell i+1, or free drainage at the bottom.
            let q_out = if i + 1 < n {
                let next = &states[i + 1];
                let k_face = 0.5 * (cur.conductivity + next.conductivity);
                let gradient = (h - heads[i + 1]) / dz + 1.0;
                if with_derivatives {
                    let dq_dhi = 0.5 * dk(i) * gradient + k_face / dz * dh(i);
                    let dq_dhj = 0.5 * dk(i + 1) * gradient - k_face / dz * dh(i + 1);
                    out.diagonal[i] -= dq_dhi / dz;
                    out.upper[i] -= dq_dhj / dz;
                    out.lower[i + 1] += dq_dhi / dz;
                    out.diagonal[i + 1] += dq_dhj / dz;
                }
                k_face * gradient
            } else {
                if with_derivatives {
                    out.bottom_gradient = dk(i);
                    out.diagonal[i] -= dk(i) / dz;
                }
                cur.conductivity
            };
            let s = if i < roots {
                let (stress, d_stress) = self.crop.stress.stress_and_derivative(h);
                let d_stress = d_stress * dh(i);
                if with_derivatives {
                    out.diagonal[i] -= d_stress * sink;
                    out.uptake_gradient[i] = d_stress * sink * dz;
                }
                stress * sink
            } else {
                0.0
            };
            out.storage[i] = (q_in - q_out) / dz - s;
            uptake += s * dz;
            q_in = q_out;
        }
        out.amounts[DRAINAGE] = q_in;
        out.amounts[UPTAKE] = uptake;
    }
}
