//! Open-loop validation of a prediction model (MODEL.md §3): recursive N-step
//! predictions from noisy windows, scored against the noise-free output.

use super::dataset::Series;
use super::rollout::Past;

/// Length of the input window p.
pub const WINDOW: usize = 20;

/// The window before step t of `series`: its supplies (`supply`, from
/// [`Series::supply`]), noisy outputs and ET0 over steps t − 20..t.
pub fn past_at<'a>(series: &'a Series, supply: &'a [f64], t: usize) -> Past<'a> {
    Past {
        u: &supply[t - WINDOW..t],
        y: &series.measured[t - WINDOW..t],
        et0: &series.et0[t - WINDOW..t],
    }
}

/// NRMSE = RMSE/(y_max − y_min) of recursive predictions at each horizon in
/// `horizons` (1-based steps ahead), over every `stride`-th start of `series`.
///
/// `predict(past, future_u, future_et0)` gets the last [`WINDOW`] supplies
/// (irrigation + rain), noisy outputs and ET0 rates before the start t (y[k]
/// is the output after u[k] was applied over step k) and the supplies and
/// ET0 of t..t+H; it returns ŷ[0..H], its predictions of y[t..t+H]. The
/// range is that of the noise-free output.
pub fn recursive_nrmse(
    series: &Series,
    horizons: &[usize],
    stride: usize,
    mut predict: impl FnMut(Past<'_>, &[f64], &[f64]) -> Vec<f64>,
) -> Vec<f64> {
    let supply = series.supply();
    let longest = horizons.iter().copied().max().unwrap_or(1);
    let y = &series.water_content;
    let (min, max) = y
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &v| {
            (a.min(v), b.max(v))
        });
    let mut sums = vec![0.0; horizons.len()];
    let mut count = 0usize;
    let mut t = WINDOW;
    while t + longest <= series.len() {
        let predicted = predict(
            past_at(series, &supply, t),
            &supply[t..t + longest],
            &series.et0[t..t + longest],
        );
        for (sum, &h) in sums.iter_mut().zip(horizons) {
            let e = predicted[h - 1] - y[t + h - 1];
            *sum += e * e;
        }
        count += 1;
        t += stride.max(1);
    }
    sums.iter()
        .map(|s| (s / count.max(1) as f64).sqrt() / (max - min))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn perfect_and_constant_predictors_score_as_expected() {
        // y[k] = sin(k/10) + 2, noise-free and measured equal.
        let y: Vec<f64> = (0..400).map(|k| (k as f64 / 10.0).sin() + 2.0).collect();
        let series = Series {
            irrigation: vec![0.0; 400],
            rain: vec![0.0; 400],
            et0: vec![0.0; 400],
            water_content: y.clone(),
            measured: y.clone(),
        };
        // A predictor that knows the truth scores 0 at every horizon.
        let truth = |past: Past<'_>, future: &[f64], _: &[f64]| {
            // recover t from the last measured value's position
            let t = y.iter().position(|v| *v == past.y[WINDOW - 1]).unwrap() + 1;
            y[t..t + future.len()].to_vec()
        };
        let scores = recursive_nrmse(&series, &[1, 10, 20], 1, truth);
        assert!(scores.iter().all(|s| *s < 1e-15), "{scores:?}");
        // Persistence (ŷ = last value) is off by |y[t+h−1] − y[t−1]|: worse with h.
        let persist =
            |past: Past<'_>, future: &[f64], _: &[f64]| vec![past.y[WINDOW - 1]; future.len()];
        let scores = recursive_nrmse(&series, &[1, 10, 20], 1, persist);
        assert!(scores[0] < scores[1] && scores[1] < scores[2], "{scores:?}");
        // one step of a sine with step 0.1 moves by at most 0.1: RMSE ≈ 0.1/√2, range 2
        assert!(
            (scores[0] - 0.1 / 2f64.sqrt() / 2.0).abs() < 0.005,
            "{}",
            scores[0]
        );
    }
}
