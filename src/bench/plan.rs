//! The robustness benchmark as a plan: one independent job per line, so any executor can run
//! it — this machine's `--jobs K` workers, or a cluster's job array (`scripts/slurm/`).
//!
//! `homing bench robustness --plan-only --out DIR` writes DIR/jobs.txt (one shell command a
//! line: line N is the Slurm array task N) and DIR/jobs.json (the same jobs with what each
//! one writes and needs, and the options the plan was made from), and prepares the inputs the
//! runs share (decoded frames and features, once per sequence). `--collect DIR` builds the
//! reports from the run folders alone, so a result does not depend on who ran the lines.
//! A job counts as finished only by what it left in its folder (its `summary.json` records
//! the line's exact command and no error, or the case study's done mark): a job killed by
//! the scheduler, a stale folder from another plan or a failed run is listed, never read.

use crate::config::ControllerKind;
use crate::error::{Error, Result};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// The plan's job list, one command a line.
pub const JOBS_TXT: &str = "jobs.txt";
/// The plan with every job's folder and inputs, and the options it was made from.
pub const JOBS_JSON: &str = "jobs.json";
/// Written by `--collect`: the lines not finished, one a line (line, tab, why).
pub const UNFINISHED_TXT: &str = "unfinished.txt";

/// What a plan was made from: enough for `--collect` to make the same grid again and to
/// check that the plan on disk is that grid.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PlanOptions {
    /// TUM folders, absolute.
    pub sequences: Vec<PathBuf>,
    pub mono: bool,
    pub controllers: Vec<ControllerKind>,
    pub quick: bool,
    pub drop_shift: f64,
    /// Config file for every run, absolute.
    pub config: Option<PathBuf>,
    /// A generated case study, absolute.
    pub case_study: Option<PathBuf>,
    /// The `homing` binary every line runs.
    pub exe: PathBuf,
}

/// What a line does.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum JobKind {
    /// One `homing run`: one row of robustness.csv.
    Run,
    /// One controller's two sessions of the case study (`homing bench case-study`).
    CaseStudy,
}

/// One line of jobs.txt.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PlannedJob {
    /// Its line in jobs.txt, from 1: the Slurm array index that runs it.
    pub line: usize,
    pub kind: JobKind,
    /// The row's sequence and perturbation (runs only).
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub sequence: Option<String>,
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub perturbation: Option<String>,
    pub controller: ControllerKind,
    /// The folder the job writes.
    pub out: PathBuf,
    /// The line's command, one argument an element.
    pub argv: Vec<String>,
    /// What the job reads: the sequence (or case study) folder, the config, and the prepared
    /// inputs of the plan (decoded frames, features); all must be on the node that runs it.
    pub needs: Vec<PathBuf>,
}

/// DIR/jobs.json.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Plan {
    pub homing_version: String,
    pub options: PlanOptions,
    pub jobs: Vec<PlannedJob>,
}

impl Plan {
    /// Writes DIR/jobs.txt and DIR/jobs.json (each atomically).
    pub fn write(&self, dir: &Path) -> Result<()> {
        let mut txt = String::new();
        for j in &self.jobs {
            txt.push_str(&shell_line(&j.argv));
            txt.push('\n');
        }
        crate::io::atomic_write(&dir.join(JOBS_TXT), txt.as_bytes())?;
        let json = serde_json::to_vec_pretty(self).map_err(|e| Error::invalid(e.to_string()))?;
        crate::io::atomic_write(&dir.join(JOBS_JSON), &json)
    }

    /// Reads DIR/jobs.json, and checks DIR/jobs.txt still holds its lines (an executor runs
    /// jobs.txt; a hand-edited line would make rows that are not the plan's).
    pub fn read(dir: &Path) -> Result<Self> {
        let path = dir.join(JOBS_JSON);
        let text = crate::error::read_text(&path)?;
        let plan: Plan = serde_json::from_str(&text)
            .map_err(|e| Error::parse(&path, e.line(), format!("not a homing plan: {e}")))?;
        if plan.homing_version != env!("CARGO_PKG_VERSION") {
            tracing::warn!(
                "{} was planned by homing {}, this is {}",
                path.display(),
                plan.homing_version,
                env!("CARGO_PKG_VERSION")
            );
        }
        let txt_path = dir.join(JOBS_TXT);
        let txt = crate::error::read_text(&txt_path)?;
        let lines: Vec<&str> = txt.lines().collect();
        for (i, j) in plan.jobs.iter().enumerate() {
            if j.line != i + 1 {
                return Err(Error::file(
                    &path,
                    format!("job {} has line {}: lines must count from 1", i + 1, j.line),
                ));
            }
            if lines.get(i).copied() != Some(shell_line(&j.argv).as_str()) {
                return Err(Error::parse(
                    &txt_path,
                    i + 1,
                    format!("is not the planned command of job {} in {JOBS_JSON}", i + 1),
                ));
            }
        }
        if lines.len() != plan.jobs.len() {
            return Err(Error::parse(
                &txt_path,
                lines.len(),
                format!(
                    "{} lines for the {} jobs of {JOBS_JSON}",
                    lines.len(),
                    plan.jobs.len()
                ),
            ));
        }
        Ok(plan)
    }
}

/// A shell word: quoted only when it has to be, so commands stay copy-pasteable.
pub(crate) fn shell_quote(s: &str) -> String {
    if !s.is_empty()
        && s.chars()
            .all(|c| c.is_ascii_alphanumeric() || "-_./:@=,+%".contains(c))
    {
        s.to_string()
    } else {
        format!("'{}'", s.replace('\'', r"'\''"))
    }
}

/// `argv` as one shell command line.
pub(crate) fn shell_line(argv: &[String]) -> String {
    argv.iter()
        .map(|a| shell_quote(a))
        .collect::<Vec<_>>()
        .join(" ")
}

/// Job lines as a Slurm `--array` list: `3,7-9,12`.
pub fn array_spec(lines: &[usize]) -> String {
    let mut sorted = lines.to_vec();
    sorted.sort_unstable();
    sorted.dedup();
    let mut parts: Vec<String> = Vec::new();
    let mut i = 0;
    while i < sorted.len() {
        let start = sorted[i];
        let mut end = start;
        while i + 1 < sorted.len() && sorted[i + 1] == end + 1 {
            i += 1;
            end = sorted[i];
        }
        parts.push(if end == start {
            start.to_string()
        } else {
            format!("{start}-{end}")
        });
        i += 1;
    }
    parts.join(",")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn array_spec_joins_runs_of_lines() {
        assert_eq!(array_spec(&[]), "");
        assert_eq!(array_spec(&[5]), "5");
        assert_eq!(array_spec(&[9, 3, 7, 8, 12, 3]), "3,7-9,12");
    }

    #[test]
    fn shell_line_quotes_only_when_needed() {
        let argv = ["/x/homing", "run", "--out", "a b", "it's"].map(String::from);
        assert_eq!(shell_line(&argv), r"/x/homing run --out 'a b' 'it'\''s'");
    }

    #[test]
    fn a_plan_whose_jobs_txt_was_edited_is_refused() {
        let tmp = tempfile::tempdir().unwrap();
        let plan = Plan {
            homing_version: env!("CARGO_PKG_VERSION").into(),
            options: PlanOptions {
                sequences: vec!["/d/seq".into()],
                mono: false,
                controllers: vec![ControllerKind::Ours],
                quick: true,
                drop_shift: 0.0,
                config: None,
                case_study: None,
                exe: "/x/homing".into(),
            },
            jobs: vec![PlannedJob {
                line: 1,
                kind: JobKind::Run,
                sequence: Some("seq".into()),
                perturbation: Some("none".into()),
                controller: ControllerKind::Ours,
                out: "/o/runs/seq/none/ours".into(),
                argv: ["/x/homing", "-q", "run"].map(String::from).to_vec(),
                needs: vec!["/d/seq".into()],
            }],
        };
        plan.write(tmp.path()).unwrap();
        assert_eq!(Plan::read(tmp.path()).unwrap(), plan);
        std::fs::write(tmp.path().join(JOBS_TXT), "/x/homing -q run --mono\n").unwrap();
        let e = Plan::read(tmp.path()).unwrap_err().to_string();
        assert!(e.contains("jobs.txt") && e.contains('1'), "{e}");
    }
}
