//! `g2r-train compare-evals`: can two evaluations of the same crops be told apart? Two runs of one recipe differ by a
//! few per cent, and "choose on validation" needs to know whether such a difference is the runs' or the split's.
//!
//! The crops of one ortho share its sun, its view and much of its ground, so their errors move together: the ortho,
//! not the crop, is the unit that varies between held-out tiles. The comparison therefore resamples whole orthos
//! (a cluster bootstrap): the candidate's learned SSE over the base's, summed over the drawn orthos, thousands of
//! times, and the central 95 % of those ratios is the interval. A resampled ratio is a base-weighted mean of the
//! per-ortho ratios, so it always lies between the smallest and the largest of them.

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;

use anyhow::{bail, Context, Result};
use rand::Rng;
use serde::Deserialize;

/// The part of an `eval` `metrics.json` a comparison reads.
#[derive(Debug, Clone, Deserialize)]
pub struct EvalRecord {
    pub split: String,
    pub per_image: Vec<ImageRecord>,
}

/// One image of an [`EvalRecord`]: its ortho and each method's SSE.
#[derive(Debug, Clone, Deserialize)]
pub struct ImageRecord {
    pub sample_id: String,
    pub ortho_id: String,
    pub metrics: BTreeMap<String, MethodSse>,
}

#[derive(Debug, Clone, Deserialize)]
pub struct MethodSse {
    pub sse: f64,
}

/// Summed SSE of one ortho's crops: base learned, candidate learned, paper-normalised Hapke.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct OrthoSse {
    pub ortho_id: String,
    pub images: usize,
    pub base: f64,
    pub candidate: f64,
    pub hapke_paper: f64,
}

/// A paired comparison of two evaluations of the same crops.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Comparison {
    pub split: String,
    pub images: usize,
    /// Learned / paper-Hapke SSE of each.
    pub base_over_hapke_paper: f64,
    pub candidate_over_hapke_paper: f64,
    /// Candidate's learned SSE over the base's (below 1: the candidate is better).
    pub candidate_over_base: f64,
    /// Central 95 % of the ratio over ortho resamples.
    pub interval_95: (f64, f64),
    pub resamples: usize,
    pub seed: u64,
    pub per_ortho: Vec<OrthoSse>,
}

impl Comparison {
    /// Whether the interval excludes 1, and on which side.
    pub fn verdict(&self) -> &'static str {
        if self.interval_95.1 < 1.0 {
            "the candidate is better"
        } else if self.interval_95.0 > 1.0 {
            "the candidate is worse"
        } else {
            "not told apart: the interval holds 1"
        }
    }
}

/// Read an `eval` output directory's `metrics.json` (or the file itself).
pub fn read_eval_record(path: &Path) -> Result<EvalRecord> {
    let file = if path.is_dir() {
        path.join("metrics.json")
    } else {
        path.to_path_buf()
    };
    let text = std::fs::read_to_string(&file).with_context(|| {
        format!(
            "{}: cannot read it; give an `eval --out` directory or its metrics.json",
            file.display()
        )
    })?;
    serde_json::from_str(&text).with_context(|| {
        format!(
            "{}: not an `eval` metrics.json (needs split and per_image); rerun `g2r-train eval`",
            file.display()
        )
    })
}

fn learned_and_paper(image: &ImageRecord, file: &str) -> Result<(f64, f64)> {
    let sse = |method: &str| {
        image.metrics.get(method).map(|m| m.sse).with_context(|| {
            format!(
                "{file}: image {} has no {method} SSE; rerun `g2r-train eval`",
                image.sample_id
            )
        })
    };
    Ok((sse("learned")?, sse("hapke_paper")?))
}

/// Pair `base` and `candidate` crop by crop (both must hold exactly the same crops of the same split) and bootstrap
/// the candidate/base ratio over orthos, `resamples` times from the stream keyed ("compare-evals", `seed`).
pub fn compare_evals(
    base: &EvalRecord,
    candidate: &EvalRecord,
    names: (&str, &str),
    resamples: usize,
    seed: u64,
) -> Result<Comparison> {
    if base.split != candidate.split {
        bail!(
            "{} is on the {} split and {} on the {} split; compare evaluations of one split",
            names.0,
            base.split,
            names.1,
            candidate.split
        );
    }
    let candidate_by_id: BTreeMap<&str, &ImageRecord> = candidate
        .per_image
        .iter()
        .map(|i| (i.sample_id.as_str(), i))
        .collect();
    let base_ids: BTreeSet<&str> = base
        .per_image
        .iter()
        .map(|i| i.sample_id.as_str())
        .collect();
    if base_ids.len() != base.per_image.len() || candidate_by_id.len() != candidate.per_image.len()
    {
        bail!(
            "{} or {} lists a crop twice; rerun `g2r-train eval`",
            names.0,
            names.1
        );
    }
    if base_ids != candidate_by_id.keys().copied().collect() {
        bail!(
            "{} and {} evaluated different crops ({} and {} images); evaluate both with the same --split and \
             --max-samples",
            names.0,
            names.1,
            base.per_image.len(),
            candidate.per_image.len()
        );
    }
    if resamples == 0 {
        bail!("--resamples must be at least 1");
    }
    let mut orthos: BTreeMap<&str, OrthoSse> = BTreeMap::new();
    for image in &base.per_image {
        let (base_learned, paper) = learned_and_paper(image, names.0)?;
        let (candidate_learned, candidate_paper) =
            learned_and_paper(candidate_by_id[image.sample_id.as_str()], names.1)?;
        // The baseline is the same rendering of the same crop in both: a difference means another dataset.
        if (paper - candidate_paper).abs() > 1e-9 * paper.abs().max(1e-30) {
            bail!(
                "{} and {} disagree on paper-Hapke's error for {} ({paper} and {candidate_paper}): not the same \
                 dataset",
                names.0,
                names.1,
                image.sample_id
            );
        }
        let o = orthos.entry(&image.ortho_id).or_insert_with(|| OrthoSse {
            ortho_id: image.ortho_id.clone(),
            images: 0,
            base: 0.0,
            candidate: 0.0,
            hapke_paper: 0.0,
        });
        o.images += 1;
        o.base += base_learned;
        o.candidate += candidate_learned;
        o.hapke_paper += paper;
    }
    let per_ortho: Vec<OrthoSse> = orthos.into_values().collect();
    let total = |f: fn(&OrthoSse) -> f64| per_ortho.iter().map(f).sum::<f64>();
    let (base_sse, candidate_sse, paper_sse) = (
        total(|o| o.base),
        total(|o| o.candidate),
        total(|o| o.hapke_paper),
    );
    if base_sse <= 0.0 {
        bail!(
            "{}: the learned SSE is zero; nothing to compare against",
            names.0
        );
    }
    let mut rng = dataset::contract::rng::keyed_rng(seed, "compare-evals", 0);
    let mut ratios: Vec<f64> = (0..resamples)
        .map(|_| {
            let (mut c, mut b) = (0.0, 0.0);
            for _ in 0..per_ortho.len() {
                let o = &per_ortho[rng.random_range(0..per_ortho.len())];
                c += o.candidate;
                b += o.base;
            }
            c / b
        })
        .collect();
    ratios.sort_by(f64::total_cmp);
    let at = |q: f64| ratios[((q * resamples as f64).floor() as usize).min(resamples - 1)];
    Ok(Comparison {
        split: base.split.clone(),
        images: base.per_image.len(),
        base_over_hapke_paper: base_sse / paper_sse,
        candidate_over_hapke_paper: candidate_sse / paper_sse,
        candidate_over_base: candidate_sse / base_sse,
        interval_95: (at(0.025), at(0.975)),
        resamples,
        seed,
        per_ortho,
    })
}

/// The comparison as Markdown: the headline, the interval and verdict, then each ortho's ratio.
pub fn comparison_markdown(c: &Comparison, names: (&str, &str)) -> String {
    let mut text = format!(
        "# {} against {} ({} split, {} images, {} orthos)\n\n",
        names.1,
        names.0,
        c.split,
        c.images,
        c.per_ortho.len()
    );
    text.push_str(&format!(
        "learned / paper-Hapke SSE: base {:.4}, candidate {:.4}\n\ncandidate / base learned SSE: **{:.4}**, 95 % \
         interval over orthos {:.4}–{:.4} ({} resamples of whole orthos, seed {}): {}.\n\n",
        c.base_over_hapke_paper,
        c.candidate_over_hapke_paper,
        c.candidate_over_base,
        c.interval_95.0,
        c.interval_95.1,
        c.resamples,
        c.seed,
        c.verdict()
    ));
    text.push_str(
        "| ortho | images | candidate / base | base / paper-Hapke |\n|---|---|---|---|\n",
    );
    for o in &c.per_ortho {
        text.push_str(&format!(
            "| {} | {} | {:.4} | {:.3} |\n",
            o.ortho_id,
            o.images,
            o.candidate / o.base,
            o.base / o.hapke_paper
        ));
    }
    text
}

/// Write `comparison.json` and `comparison.md` into `out` (created), each atomically, and the `provenance.json`
/// of this run beside them.
pub fn write_comparison(c: &Comparison, markdown: &str, out: &Path) -> Result<()> {
    std::fs::create_dir_all(out)
        .with_context(|| format!("{}: cannot create the output directory", out.display()))?;
    dataset::files::write_json_atomic(&out.join("comparison.json"), c)?;
    dataset::files::write_text_atomic(&out.join("comparison.md"), markdown)?;
    dataset::provenance::Provenance::capture().write(&out.join("provenance.json"))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn image(id: &str, ortho: &str, learned: f64, paper: f64) -> ImageRecord {
        ImageRecord {
            sample_id: id.into(),
            ortho_id: ortho.into(),
            metrics: [
                ("learned".to_string(), MethodSse { sse: learned }),
                ("hapke_paper".to_string(), MethodSse { sse: paper }),
            ]
            .into(),
        }
    }

    /// Twelve crops over four orthos with uneven errors.
    fn base() -> EvalRecord {
        EvalRecord {
            split: "val".into(),
            per_image: (0..12)
                .map(|k| {
                    let learned = 0.5 + 0.37 * ((k * 7) % 5) as f64;
                    image(
                        &format!("s{k}"),
                        &format!("M{}", k % 4),
                        learned,
                        2.0 + k as f64,
                    )
                })
                .collect(),
        }
    }

    fn scaled(record: &EvalRecord, factor: impl Fn(&ImageRecord) -> f64) -> EvalRecord {
        let mut out = record.clone();
        for i in &mut out.per_image {
            let f = factor(i);
            i.metrics.get_mut("learned").unwrap().sse *= f;
        }
        out
    }

    #[test]
    fn an_evaluation_against_itself_is_one_with_no_spread() {
        let c = compare_evals(&base(), &base(), ("a", "b"), 500, 1).unwrap();
        assert_eq!(c.candidate_over_base, 1.0);
        assert_eq!(c.interval_95, (1.0, 1.0));
        assert_eq!(c.verdict(), "not told apart: the interval holds 1");
        // The headline is the plain ratio of sums.
        let learned: f64 = base()
            .per_image
            .iter()
            .map(|i| i.metrics["learned"].sse)
            .sum();
        let paper: f64 = (0..12).map(|k| 2.0 + k as f64).sum();
        assert!((c.base_over_hapke_paper - learned / paper).abs() < 1e-15);
    }

    #[test]
    fn a_uniform_improvement_is_told_apart_whatever_the_resample() {
        let c = compare_evals(&base(), &scaled(&base(), |_| 0.8), ("a", "b"), 500, 1).unwrap();
        assert!((c.candidate_over_base - 0.8).abs() < 1e-12);
        assert!((c.interval_95.0 - 0.8).abs() < 1e-12 && (c.interval_95.1 - 0.8).abs() < 1e-12);
        assert_eq!(c.verdict(), "the candidate is better");
        let worse = compare_evals(&base(), &scaled(&base(), |_| 1.1), ("a", "b"), 500, 1).unwrap();
        assert_eq!(worse.verdict(), "the candidate is worse");
    }

    #[test]
    fn the_interval_lies_within_the_per_ortho_ratios_and_holds_the_estimate() {
        // Better on two orthos, worse on the others: the resampled ratios are base-weighted means of the
        // per-ortho ratios, so they cannot leave [min, max] of those.
        let factors = [0.6, 1.3, 0.9, 1.2];
        let candidate = scaled(&base(), |i| {
            factors[i.ortho_id[1..].parse::<usize>().unwrap()]
        });
        let c = compare_evals(&base(), &candidate, ("a", "b"), 4000, 7).unwrap();
        let per: Vec<f64> = c.per_ortho.iter().map(|o| o.candidate / o.base).collect();
        for (p, f) in per.iter().zip(factors) {
            assert!((p - f).abs() < 1e-12);
        }
        assert!(c.interval_95.0 >= 0.6 - 1e-12 && c.interval_95.1 <= 1.3 + 1e-12);
        assert!(c.interval_95.0 < c.candidate_over_base && c.candidate_over_base < c.interval_95.1);
        assert_eq!(c.verdict(), "not told apart: the interval holds 1");
        // Same seed, same interval.
        assert_eq!(
            compare_evals(&base(), &candidate, ("a", "b"), 4000, 7).unwrap(),
            c
        );
    }

    #[test]
    fn the_order_of_the_crops_does_not_matter() {
        let mut shuffled = scaled(&base(), |i| if i.ortho_id == "M2" { 0.7 } else { 1.05 });
        let c = compare_evals(&base(), &shuffled, ("a", "b"), 1000, 3).unwrap();
        shuffled.per_image.reverse();
        assert_eq!(
            compare_evals(&base(), &shuffled, ("a", "b"), 1000, 3).unwrap(),
            c
        );
    }

    #[test]
    fn different_crops_splits_or_datasets_are_refused_naming_both() {
        let mut fewer = base();
        fewer.per_image.pop();
        let e = compare_evals(&base(), &fewer, ("runA", "runB"), 10, 1).unwrap_err();
        assert!(e.to_string().contains("runA") && e.to_string().contains("different crops"));
        let mut test = base();
        test.split = "test".into();
        let e = compare_evals(&base(), &test, ("runA", "runB"), 10, 1).unwrap_err();
        assert!(e.to_string().contains("test split"));
        let mut other = base();
        other.per_image[3]
            .metrics
            .get_mut("hapke_paper")
            .unwrap()
            .sse *= 1.5;
        let e = compare_evals(&base(), &other, ("runA", "runB"), 10, 1).unwrap_err();
        assert!(e.to_string().contains("not the same dataset"));
    }
}
