//! A per-field surrogate, as the daemon's training job makes it, against a
//! from-scratch training on the same soil, scored on the same fresh data.
//!
//! ```sh
//! cargo run --release --example finetune -- loam /tmp/models-loam
//! ```
//!
//! Arguments: the texture, the folder of a from-scratch training of it
//! (`rootzone train --soil loam --out /tmp/models-loam`), and optionally
//! the data seed (default 1) and, to try another plan than the daemon's
//! default, the impulse samples, the sub-model samples and the epochs. The fine-tuning runs on one thread with the
//! daemon's default plan; the data cache is a temporary folder, so the
//! time includes generating the data.

use std::path::PathBuf;
use std::time::Instant;

use rootzone::soil::Texture;
use rootzone::surrogate::dataset::load_or_generate;
use rootzone::surrogate::finetune::{FineTunePlan, fine_tune, validation_seed};
use rootzone::surrogate::pipeline::{
    TWO_LAYER_FILE, cache_name, nrmse_scores, training_weather, validation_spec_for,
};
use rootzone::surrogate::{ModelFile, Surrogate};

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let usage = "usage: finetune TEXTURE FROM_SCRATCH_DIR [SEED [IMPULSE SUB EPOCHS]]";
    let (Some(texture), Some(scratch)) = (args.first(), args.get(1)) else {
        eprintln!("{usage}");
        std::process::exit(2);
    };
    let texture: Texture = texture.parse().unwrap_or_else(|e| {
        eprintln!("{usage}: {e}");
        std::process::exit(2)
    });
    let number = |i: usize, default: u64| -> u64 {
        args.get(i).map_or(default, |s| {
            s.parse().unwrap_or_else(|_| {
                eprintln!("{usage}: argument {} must be a whole number", i + 1);
                std::process::exit(2)
            })
        })
    };
    let seed = number(2, 1);
    let soil = texture.parameters();
    let name = texture.to_string();
    let shipped = ModelFile::load(
        &PathBuf::from(env!("CARGO_MANIFEST_DIR"))
            .join("models")
            .join(TWO_LAYER_FILE),
    )
    .expect("the shipped two-layer model loads");
    let Surrogate::TwoLayer(base) = &shipped.model else {
        panic!("the shipped two-layer file holds a two-layer model");
    };
    let cache = tempfile::tempdir().expect("a temporary folder");
    let mut plan = FineTunePlan::default_job();
    plan.impulse_samples = number(3, plan.impulse_samples as u64) as usize;
    plan.sub_model_samples = number(4, plan.sub_model_samples as u64) as usize;
    plan.config.max_epochs = number(5, plan.config.max_epochs as u64) as usize;
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .expect("a one-thread pool");
    let start = Instant::now();
    let tuned = pool
        .install(|| {
            fine_tune(
                base,
                "shipped",
                soil,
                &name,
                &plan,
                seed,
                cache.path(),
                |_| {},
                &|| false,
            )
        })
        .expect("the fine-tuning runs");
    let seconds = start.elapsed().as_secs_f64();
    // the from-scratch model on the very validation set the job scored on
    let scratch = ModelFile::load(&PathBuf::from(scratch).join(TWO_LAYER_FILE))
        .expect("the from-scratch two-layer model loads");
    let spec = validation_spec_for(3, plan.validation_samples, validation_seed(seed), &soil);
    let validation = load_or_generate(
        &spec,
        &cache_name(&name),
        &rootzone::soil::FieldSettings {
            soil,
            ..Default::default()
        },
        training_weather().steps(),
        cache.path(),
    )
    .expect("the validation data");
    let from_scratch = nrmse_scores(&mut scratch.predictor(), &validation);
    println!("soil {name}, data seed {seed}, one thread");
    println!(
        "fine-tuned from the shipped network: {seconds:.1} s, {} epochs",
        tuned.epochs
    );
    println!(
        "NRMSE at 1/10/20 steps on fresh {name} data ({} samples):",
        validation.len()
    );
    let show = |what: &str, s: [f64; 3]| {
        println!("  {what:<24} {:.4} {:.4} {:.4}", s[0], s[1], s[2]);
    };
    show("fine-tuned", tuned.scores);
    show("from scratch", from_scratch);
    show("shipped (sandy loam)", tuned.base_scores);
    let worst = (0..3)
        .map(|i| tuned.scores[i] / from_scratch[i] - 1.0)
        .fold(f64::NEG_INFINITY, f64::max);
    println!(
        "fine-tuned against from scratch: at most {:+.1} %",
        100.0 * worst
    );
}
