//! Progress of long steps on stderr: a bar on a terminal, a log line every
//! few seconds otherwise (a CI log, a batch job), nothing when disabled.
//! Steps that end within [`QUIET_FOR`] print nothing in log mode.

use std::io::IsTerminal;
use std::sync::Mutex;
use std::time::{Duration, Instant};

/// Log mode stays silent for steps shorter than this.
pub const QUIET_FOR: Duration = Duration::from_secs(2);
/// Time between two log lines.
pub const LOG_EVERY: Duration = Duration::from_secs(10);

/// One step with a known amount of work (`total` units).
#[derive(Debug)]
pub struct Task {
    mode: Mode,
    label: String,
    unit: &'static str,
    /// `None`: open-ended (a count, no fraction).
    total: Option<u64>,
    start: Instant,
    /// Log mode: when the last line was printed (`None`: none yet) and the
    /// position.
    state: Mutex<(Option<Instant>, u64)>,
}

#[derive(Debug)]
enum Mode {
    Off,
    Bar(indicatif::ProgressBar),
    Log,
}

impl Task {
    /// A step called `label` of `total` `unit`s; `enabled = false` shows
    /// nothing.
    pub fn new(enabled: bool, label: impl Into<String>, total: u64, unit: &'static str) -> Task {
        Task::with_total(enabled, label.into(), Some(total), unit)
    }

    /// A step of unknown length that counts `unit`s (e.g. evaluations).
    pub fn open(enabled: bool, label: impl Into<String>, unit: &'static str) -> Task {
        Task::with_total(enabled, label.into(), None, unit)
    }

    fn with_total(enabled: bool, label: String, total: Option<u64>, unit: &'static str) -> Task {
        let mode = if !enabled {
            Mode::Off
        } else if std::io::stderr().is_terminal() {
            let bar = indicatif::ProgressBar::with_draw_target(
                total,
                indicatif::ProgressDrawTarget::stderr(),
            );
            let template = match total {
                Some(_) => format!(
                    "{{spinner}} {label} [{{elapsed_precise}}] {{wide_bar}} {{pos}}/{{len}} {unit} (ETA {{eta}})"
                ),
                None => format!("{{spinner}} {label} [{{elapsed_precise}}] {{pos}} {unit}"),
            };
            if let Ok(style) = indicatif::ProgressStyle::with_template(&template) {
                bar.set_style(style);
            }
            if total.is_none() {
                bar.enable_steady_tick(Duration::from_millis(200));
            }
            Mode::Bar(bar)
        } else {
            Mode::Log
        };
        Task {
            mode,
            label,
            unit,
            total,
            start: Instant::now(),
            state: Mutex::new((None, 0)),
        }
    }

    /// Sets the amount done.
    pub fn set(&self, done: u64) {
        match &self.mode {
            Mode::Off => {}
            Mode::Bar(bar) => bar.set_position(done),
            Mode::Log => self.advance(|_| done),
        }
    }

    /// Adds `n` to the amount done.
    pub fn inc(&self, n: u64) {
        match &self.mode {
            Mode::Off => {}
            Mode::Bar(bar) => bar.inc(n),
            Mode::Log => self.advance(|done| done + n),
        }
    }

    /// Log mode: moves the position (under one lock, so that threads
    /// counting at once lose nothing) and prints a line when one is due.
    fn advance(&self, to: impl FnOnce(u64) -> u64) {
        let mut st = self.state.lock().unwrap_or_else(|e| e.into_inner());
        st.1 = to(st.1);
        let done = st.1;
        let due = match st.0 {
            None => self.start.elapsed() >= QUIET_FOR,
            Some(t) => t.elapsed() >= LOG_EVERY,
        };
        if due && self.total.is_none_or(|t| done < t) {
            st.0 = Some(Instant::now());
            self.line(done, "");
        }
    }

    /// Ends the step: clears the bar; in log mode a closing line if the step
    /// printed any.
    pub fn finish(&self) {
        match &self.mode {
            Mode::Off => {}
            Mode::Bar(bar) => bar.finish_and_clear(),
            Mode::Log => {
                let st = self.state.lock().unwrap_or_else(|e| e.into_inner());
                if st.0.is_some() {
                    self.line(self.total.unwrap_or(st.1), " done");
                }
            }
        }
    }

    fn line(&self, done: u64, tail: &str) {
        let t = self.start.elapsed().as_secs_f64();
        match self.total {
            Some(total) => {
                let pct = 100.0 * done as f64 / total.max(1) as f64;
                eprintln!(
                    "{}: {done}/{total} {} ({pct:.0} %) after {t:.0} s{tail}",
                    self.label, self.unit
                );
            }
            None => eprintln!("{}: {done} {} after {t:.0} s{tail}", self.label, self.unit),
        }
    }
}

/// A step of unknown length: a spinner on a terminal, a start and an end
/// line otherwise if it runs past [`QUIET_FOR`].
pub fn step<T>(enabled: bool, label: &str, f: impl FnOnce() -> T) -> T {
    let task = Task::new(enabled, label, 1, "step");
    if let Mode::Bar(bar) = &task.mode {
        if let Ok(style) = indicatif::ProgressStyle::with_template(&format!(
            "{{spinner}} {label} [{{elapsed_precise}}]"
        )) {
            bar.set_style(style);
        }
        bar.enable_steady_tick(Duration::from_millis(200));
    } else if matches!(task.mode, Mode::Log) {
        eprintln!("{label} …");
    }
    let out = f();
    if matches!(task.mode, Mode::Log) {
        eprintln!(
            "{label}: done in {:.1} s",
            task.start.elapsed().as_secs_f64()
        );
    }
    task.finish();
    out
}
