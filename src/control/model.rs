//! Prediction models behind one interface.

use crate::surrogate::Predictor;
use crate::surrogate::evaluate::WINDOW;

/// A prediction failed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("prediction model: {0}")]
pub struct ModelError(pub String);

/// The N-step prediction of the output θ for a plan of irrigation rates
/// (m/s), given the state the model holds (its past window, bias, forecast),
/// and its Jacobian `jac[k·N + j] = dŷ_k/du_j`.
pub trait PredictionModel: Send {
    fn predict(&mut self, plan: &[f64], out: &mut [f64]) -> Result<(), ModelError>;
    fn predict_with_jacobian(
        &mut self,
        plan: &[f64],
        out: &mut [f64],
        jac: &mut [f64],
    ) -> Result<(), ModelError>;
}

/// A surrogate ([`Predictor`]) with its window of applied inputs and measured
/// outputs and an additive bias correction.
#[derive(Debug, Clone)]
pub struct SurrogateModel {
    pub predictor: Predictor,
    /// u[t − 20..t] (m/s), oldest first.
    pub past_u: Vec<f64>,
    /// Measured y[t − 20..t].
    pub past_y: Vec<f64>,
    pub bias: f64,
}

impl SurrogateModel {
    /// A model whose window is padded with (u = 0, y = `first`), as before 20
    /// samples exist (MODEL.md §4).
    pub fn padded(predictor: Predictor, first: f64) -> SurrogateModel {
        SurrogateModel {
            predictor,
            past_u: vec![0.0; WINDOW],
            past_y: vec![first; WINDOW],
            bias: 0.0,
        }
    }

    /// Shifts the window by one sample: `u` applied over the last step, `y`
    /// measured at its end.
    pub fn push(&mut self, u: f64, y: f64) {
        self.past_u.remove(0);
        self.past_u.push(u);
        self.past_y.remove(0);
        self.past_y.push(y);
    }
}

fn finite(out: &[f64]) -> Result<(), ModelError> {
    match out.iter().position(|v| !v.is_finite()) {
        None => Ok(()),
        Some(k) => Err(ModelError(format!("non-finite prediction at step {k}"))),
    }
}

impl PredictionModel for SurrogateModel {
    fn predict(&mut self, plan: &[f64], out: &mut [f64]) -> Result<(), ModelError> {
        self.predictor
            .predict(&self.past_u, &self.past_y, plan, self.bias, out)
            .map_err(|e| ModelError(e.to_string()))?;
        finite(out)
    }

    fn predict_with_jacobian(
        &mut self,
        plan: &[f64],
        out: &mut [f64],
        jac: &mut [f64],
    ) -> Result<(), ModelError> {
        self.predictor
            .predict_with_jacobian(&self.past_u, &self.past_y, plan, self.bias, out, jac)
            .map_err(|e| ModelError(e.to_string()))?;
        finite(out)?;
        finite(jac)
    }
}
