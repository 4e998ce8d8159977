//! The paper's §2.7 example: a cantilever with a bolted mid-span connection, updated with a
//! coarser model whose Young's modulus is wrong (case I: × 1.5, case II: × 0.6).

use boltwatch::core::model::Model;
use boltwatch::core::updating::{
    Evaluator, MeasuredData, ModeMatching, ModeMatchingOptions, ModeMatchingResult,
};

use super::common::{load_model, simulated_data};

const THETA_TRUE: f64 = 0.5;
const N_MODES: usize = 4;
/// "A coefficient of variation of the modal data equal to 1 %".
const COV: f64 = 0.01;
const NSD: f64 = 0.01;
const SEED: u64 = 27;

/// Data from `cantilever-truth` at θ = 0.5 (4 modes, all 10 channels), after checking that
/// the truth and both case models have the same channel names in the same order (so the
/// channel indices of the data are valid for the case models).
fn truth_data(noisy: bool) -> (MeasuredData, Model, Model) {
    let truth = load_model("cantilever-truth");
    let case1 = load_model("cantilever-case1");
    let case2 = load_model("cantilever-case2");
    let names =
        |m: &Model| -> Vec<String> { m.channels().iter().map(|c| c.name.clone()).collect() };
    assert_eq!(truth.channels().len(), 10);
    assert_eq!(
        names(&truth),
        names(&case1),
        "case I channels differ from the truth's"
    );
    assert_eq!(
        names(&truth),
        names(&case2),
        "case II channels differ from the truth's"
    );
    assert_eq!(truth.n_params(), 1);
    assert_eq!(case1.n_params(), 1);
    assert_eq!(case2.n_params(), 1);
    let data = simulated_data(&truth, &[THETA_TRUE], N_MODES, COV, NSD, noisy, SEED);
    (data, case1, case2)
}

fn update(model: &Model, data: &MeasuredData) -> ModeMatchingResult {
    let mut mm = ModeMatching::new(Evaluator::new(model).unwrap());
    mm.run(model, data, &[1.0], &ModeMatchingOptions::default())
        .unwrap()
}

fn report(label: &str, res: &ModeMatchingResult) {
    println!(
        "{label}: θ = {:.4} ± {:.4} (σ), {:?} after {} iterations ({} evaluations), ε = {:.4e}, pairing {:?}",
        res.theta[0],
        res.std()[0],
        res.termination,
        res.iterations,
        res.evaluations,
        res.epsilon(),
        res.last.pairing
    );
}

/// Noisy data (1 % frequency CoV and 1 % shape NSD, fixed seed), weighted by (28). The
/// paper: case I (E too high) ends about 20 % below θ = 0.5, case II close to 0.5. Found
/// here (seed 27): θ_I = 0.470, θ_II = 0.407. Under model error the estimate is whatever
/// balances the frequency and shape residuals, so it moves with their relative weight;
/// `paper_finding_is_one_weighting_of_a_family` shows the paper's pair at an eigenvalue σ
/// of 1.5 % and this pair at 2 % (= 1 % frequency CoV). Asserted here: both converge,
/// θ_I < 0.5, |θ_II − 0.5| ≤ 0.15.
#[test]
fn cantilever_cases_i_and_ii_noisy() {
    let (data, case1, case2) = truth_data(true);
    let r1 = update(&case1, &data);
    let r2 = update(&case2, &data);
    report("case I  (E × 1.5), noisy", &r1);
    report("case II (E × 0.6), noisy", &r2);
    assert!(r1.converged(), "case I: {:?}", r1.termination);
    assert!(r2.converged(), "case II: {:?}", r2.termination);
    assert!(
        r1.theta[0] < THETA_TRUE,
        "case I: θ = {} is not below {THETA_TRUE}",
        r1.theta[0]
    );
    assert!(
        (r2.theta[0] - THETA_TRUE).abs() <= 0.15,
        "case II: θ = {} is not within {THETA_TRUE} ± 0.15",
        r2.theta[0]
    );
}

/// Noise-free data: the bias due to the model error (wrong E, coarser mesh) alone. Same
/// assertions as the noisy case.
#[test]
fn cantilever_cases_noise_free_bias() {
    let (data, case1, case2) = truth_data(false);
    let r1 = update(&case1, &data);
    let r2 = update(&case2, &data);
    report("case I  (E × 1.5), noise-free", &r1);
    report("case II (E × 0.6), noise-free", &r2);
    assert!(r1.converged(), "case I: {:?}", r1.termination);
    assert!(r2.converged(), "case II: {:?}", r2.termination);
    assert!(r1.theta[0] < THETA_TRUE, "case I: θ = {}", r1.theta[0]);
    assert!(
        (r2.theta[0] - THETA_TRUE).abs() <= 0.15,
        "case II: θ = {}",
        r2.theta[0]
    );
}

/// Mode matching on noise-free data (model error only) with Σ_M diagonal: shapes σ = 1 % of
/// their RMS, eigenvalues σ = f·λ̂ for several f. Frequencies alone pull case I down and
/// case II up (the stiffness absorbs the E error through the frequencies: 0.28 / 2.15);
/// shapes alone the other way (0.75 / 0.30). Every weighting lands between, moving
/// monotonically with f. At f = 0.015 both of the paper's findings hold: case I about 20 %
/// low (asserted 0.40 ± 0.025) and case II close to 0.5 (asserted ± 0.025); measured
/// 0.409 / 0.498. At f = 0.02, i.e. our default reading of "1 % CoV" as a frequency CoV
/// (λ ∝ f², so σ_λ = 2·V^f·λ), they are 0.470 / 0.407. The paper's CoV of 1 % "of the modal
/// data" reads as an eigenvalue CoV (f = 0.01: 0.343 / 0.742), which does not give its
/// figures either; its exact Σ_M is not recoverable from the text.
#[test]
fn paper_finding_is_one_weighting_of_a_family() {
    let (base, case1, case2) = truth_data(false);
    let with = |f: Option<f64>, shapes: bool| {
        let mut d = base.clone();
        for m in &mut d.modes {
            match f {
                Some(f) => m.sigma_lambda = f * m.lambda,
                None => m.sigma_lambda = 1e6 * m.lambda,
            }
            if !shapes {
                m.shape = None;
            }
        }
        let t1 = update(&case1, &d);
        let t2 = update(&case2, &d);
        assert!(t1.converged() && t2.converged(), "f = {f:?}");
        println!(
            "σ_λ/λ = {f:?}, shapes {shapes}: θ_I = {:.4}, θ_II = {:.4}",
            t1.theta[0], t2.theta[0]
        );
        (t1.theta[0], t2.theta[0])
    };
    let freq_only = with(Some(0.01), false);
    let shape_only = with(None, true);
    assert!(freq_only.0 < 0.3 && freq_only.1 > 2.0, "{freq_only:?}");
    assert!(shape_only.0 > 0.7 && shape_only.1 < 0.32, "{shape_only:?}");
    let mut last = freq_only;
    for f in [0.01, 0.015, 0.02, 0.04] {
        let t = with(Some(f), true);
        assert!(
            t.0 > last.0 && t.1 < last.1,
            "not monotone at f = {f}: {t:?} after {last:?}"
        );
        assert!(t.0 < shape_only.0 && t.1 > shape_only.1);
        if f == 0.015 {
            assert!((t.0 - 0.40).abs() <= 0.025, "case I at f = 0.015: {}", t.0);
            assert!((t.1 - 0.50).abs() <= 0.025, "case II at f = 0.015: {}", t.1);
        }
        last = t;
    }
}
