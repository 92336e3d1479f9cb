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
    total: u64,
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
        let label = label.into();
        let mode = if !enabled {
            Mode::Off
        } else if std::io::stderr().is_terminal() {
            let bar = indicatif::ProgressBar::with_draw_target(
                Some(total),
                indicatif::ProgressDrawTarget::stderr(),
            );
            if let Ok(style) = indicatif::ProgressStyle::with_template(&format!(
                "{{spinner}} {label} [{{elapsed_precise}}] {{wide_bar}} {{pos}}/{{len}} {unit} (ETA {{eta}})"
            )) {
                bar.set_style(style);
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
            Mode::Log => {
                let mut st = self.state.lock().unwrap_or_else(|e| e.into_inner());
                st.1 = done;
                let due = match st.0 {
                    None => self.start.elapsed() >= QUIET_FOR,
                    Some(t) => t.elapsed() >= LOG_EVERY,
                };
                if due && done < self.total {
                    st.0 = Some(Instant::now());
                    self.line(done, "");
                }
            }
        }
    }

    /// Adds `n` to the amount done.
    pub fn inc(&self, n: u64) {
        let done = {
            let st = self.state.lock().unwrap_or_else(|e| e.into_inner());
            st.1 + n
        };
        self.set(done);
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
                    self.line(self.total, " done");
                }
            }
        }
    }

    fn line(&self, done: u64, tail: &str) {
        let pct = 100.0 * done as f64 / self.total.max(1) as f64;
        eprintln!(
            "{}: {done}/{} {} ({pct:.0} %) after {:.0} s{tail}",
            self.label,
            self.total,
            self.unit,
            self.start.elapsed().as_secs_f64()
        );
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
