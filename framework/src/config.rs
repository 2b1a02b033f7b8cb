//! Configuration files (seed 000, 6.4): one TOML file per module, plus the shared machinery every
//! file format of the workbench uses to report errors as `file:line:col: message`.
//!
//! A module file has two tables: `[framework]` with the keys the framework needs (period, default
//! execution context, enabled commands, watchdog budgets) and `[params]` with the module's own
//! parameters, deserialized into the module's `Params` type. Unknown keys are errors, so a typo is
//! reported with its file, line and key instead of silently falling back to a default.
//!
//! ```toml
//! [framework]
//! period_s = 0.1                                  # absent: aperiodic (runs when messages arrive)
//! context = { mode = "dry-run", purpose = "mission" }
//! commands = ["reset", "add"]                     # absent: every bound command is enabled
//! overrun_budget = 3                              # consecutive overruns tolerated before Safe
//!
//! [params]
//! gain = 2.0
//! ```

use crate::exec_context::ExecContext;
use crate::time::Duration;
use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};
use std::fmt;
use std::ops::Range;
use std::path::{Path, PathBuf};

/// An error in a configuration or description file, located by file, line, column and key.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub struct ConfigError {
    /// The file (or a description of the source, e.g. `<inline config of module 'x'>`).
    pub file: String,
    /// 1-based line (0 when the problem has no position, e.g. the file cannot be read).
    pub line: usize,
    /// 1-based column.
    pub col: usize,
    /// Dotted key path, when known (`framework.period_s`).
    pub key: Option<String>,
    /// What is wrong.
    pub message: String,
}

impl fmt::Display for ConfigError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if self.line > 0 {
            write!(f, "{}:{}:{}: ", self.file, self.line, self.col)?;
        } else {
            write!(f, "{}: ", self.file)?;
        }
        if let Some(k) = &self.key {
            write!(f, "key `{k}`: ")?;
        }
        f.write_str(&self.message)
    }
}

/// A number as a message shows it: plainly when it is of everyday size, in scientific notation
/// when it is huge or tiny (a 1e300 s timeout is not printed as 301 digits).
pub fn num(v: f64) -> String {
    if v == 0.0 || !v.is_finite() || (1e-4..1e9).contains(&v.abs()) {
        format!("{v}")
    } else {
        format!("{v:e}")
    }
}

/// The first number in `doc` that is not finite (NaN or infinite), with its key path.
pub fn non_finite(doc: &toml::Table, path: &mut Vec<String>) -> Option<(Vec<String>, f64)> {
    fn walk(v: &toml::Value, path: &mut Vec<String>) -> Option<(Vec<String>, f64)> {
        match v {
            toml::Value::Float(f) if !f.is_finite() => Some((path.clone(), *f)),
            toml::Value::Table(t) => non_finite(t, path),
            toml::Value::Array(a) => a.iter().enumerate().find_map(|(i, x)| {
                path.push(i.to_string());
                let r = walk(x, path);
                path.pop();
                r
            }),
            _ => None,
        }
    }
    doc.iter().find_map(|(k, v)| {
        path.push(k.clone());
        let r = walk(v, path);
        path.pop();
        r
    })
}

/// A text being parsed, with its origin, for locating errors.
#[derive(Clone, Copy, Debug)]
pub struct Source<'a> {
    /// File name or description.
    pub origin: &'a str,
    /// The text.
    pub text: &'a str,
}

impl<'a> Source<'a> {
    /// A source from its origin and text.
    pub fn new(origin: &'a str, text: &'a str) -> Self {
        Source { origin, text }
    }

    /// Line and column (1-based, in characters) of a byte offset.
    pub fn line_col(&self, offset: usize) -> (usize, usize) {
        let offset = offset.min(self.text.len());
        let before = &self.text[..offset];
        let line = before.matches('\n').count() + 1;
        let col = before.rsplit('\n').next().map(|l| l.chars().count()).unwrap_or(0) + 1;
        (line, col)
    }

    /// An error at a byte span.
    pub fn error_at(
        &self,
        span: Option<Range<usize>>,
        key: Option<String>,
        message: impl Into<String>,
    ) -> ConfigError {
        let (line, col) = span.map(|s| self.line_col(s.start)).unwrap_or((1, 1));
        ConfigError { file: self.origin.to_string(), line, col, key, message: message.into() }
    }

    /// An error at a dotted key path (`framework.period_s`), located in the text if the key is present.
    pub fn error_at_key(&self, key: &str, message: impl Into<String>) -> ConfigError {
        let path: Vec<&str> = key.split('.').collect();
        self.error_at(locate_key(self.text, &path), Some(key.to_string()), message)
    }

    /// Deserializes the whole text as TOML into `T`, with located, keyed errors.
    pub fn parse<T: DeserializeOwned>(&self) -> Result<T, ConfigError> {
        let de = toml::de::Deserializer::parse(self.text)
            .map_err(|e| self.error_at(e.span(), None, e.message()))?;
        serde_path_to_error::deserialize(de).map_err(|e| {
            let key = e.path().to_string();
            let key = (key != "." && !key.is_empty()).then_some(key);
            let inner = e.into_inner();
            let span = inner.span().or_else(|| {
                key.as_deref().and_then(|k| locate_key(self.text, &k.split('.').collect::<Vec<_>>()))
            });
            self.error_at(span, key, inner.message())
        })
    }
}

/// The byte span of a key's value (or of the key itself if the value has no span) in a TOML text.
/// Path parts that are numbers index arrays (`objects.2.name`).
pub fn locate_key(text: &str, path: &[&str]) -> Option<Range<usize>> {
    use toml::de::DeValue;
    let doc = toml::de::DeTable::parse(text).ok()?;
    let mut value: &DeValue<'_> = &DeValue::Table(doc.get_ref().clone());
    let mut span = None;
    for part in path {
        let (k_span, v) = match value {
            DeValue::Table(t) => {
                let (k, v) = t.iter().find(|(k, _)| k.get_ref().as_ref() == *part)?;
                (k.span(), v)
            }
            DeValue::Array(a) => {
                let v = a.get(part.parse::<usize>().ok()?)?;
                (v.span(), v)
            }
            _ => return span,
        };
        span = Some(if v.span().is_empty() { k_span } else { v.span() });
        value = v.get_ref();
    }
    span
}

/// Reads a file to a string, with a located error naming the file.
pub fn read_file(path: &Path) -> Result<String, ConfigError> {
    std::fs::read_to_string(path).map_err(|e| ConfigError {
        file: path.display().to_string(),
        line: 0,
        col: 0,
        key: None,
        message: format!("cannot read file: {e}"),
    })
}

/// Parameters of a module that has none: an empty `[params]` table (any key is an error).
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NoParams {}

/// The `[framework]` table of a module configuration file.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FrameworkKeys {
    /// Period of a periodic module, in seconds; absent for an aperiodic module.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub period_s: Option<f64>,
    /// Default execution context.
    #[serde(default)]
    pub context: ExecContext,
    /// Commands enabled; absent means every bound command.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub commands: Option<Vec<String>>,
    /// Deadline of one cycle in seconds; absent means the period.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub deadline_s: Option<f64>,
    /// Consecutive deadline overruns tolerated before the watchdog isolates the module.
    #[serde(default = "default_overrun_budget")]
    pub overrun_budget: u32,
    /// Time a step may stay busy before the watchdog declares the module hung, in seconds. A remote
    /// module's host must answer each step within it.
    #[serde(default = "default_hang_timeout")]
    pub hang_timeout_s: f64,
    /// Runs the module remotely on this host (a `rover-twin module-host` endpoint, e.g.
    /// `tcp/127.0.0.1:7450`); absent: in this process.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub host: Option<String>,
}

fn default_overrun_budget() -> u32 {
    3
}
fn default_hang_timeout() -> f64 {
    2.0
}

impl Default for FrameworkKeys {
    fn default() -> Self {
        FrameworkKeys {
            period_s: None,
            context: ExecContext::default(),
            commands: None,
            deadline_s: None,
            overrun_budget: default_overrun_budget(),
            hang_timeout_s: default_hang_timeout(),
            host: None,
        }
    }
}

/// How a module is scheduled.
#[derive(Copy, Clone, Debug, PartialEq, Eq)]
pub enum Schedule {
    /// Runs its state function once per period.
    Periodic(Duration),
    /// Runs when messages arrive.
    Aperiodic,
}

impl FrameworkKeys {
    /// The schedule these keys describe.
    pub fn schedule(&self) -> Schedule {
        match self.period_s {
            Some(p) => Schedule::Periodic(Duration::from_secs_f64(p)),
            None => Schedule::Aperiodic,
        }
    }
    /// The cycle deadline (the period unless set).
    pub fn deadline(&self) -> Option<Duration> {
        self.deadline_s.or(self.period_s).map(Duration::from_secs_f64)
    }
    /// Checks the values (the types were checked by deserialization).
    pub fn validate(&self, src: &Source<'_>) -> Result<(), ConfigError> {
        /// Longest period, deadline or hang timeout, s (a day: beyond it a value is a typo).
        const MAX_S: f64 = 86_400.0;
        let positive = |key: &str, v: Option<f64>| match v {
            Some(v) if !(v.is_finite() && v > 0.0 && v <= MAX_S) => Err(
                src.error_at_key(key, format!("must be a positive number of seconds up to {MAX_S}, got {v}"))
            ),
            _ => Ok(()),
        };
        positive("framework.period_s", self.period_s)?;
        positive("framework.deadline_s", self.deadline_s)?;
        positive("framework.hang_timeout_s", Some(self.hang_timeout_s))?;
        if let Some(h) = &self.host
            && (h.is_empty() || h.contains(char::is_whitespace) || !h.contains('/'))
        {
            return Err(
                src.error_at_key("framework.host", format!("'{h}': expected an endpoint like tcp/HOST:PORT"))
            );
        }
        if let Some(p) = self.period_s
            && Duration::from_secs_f64(p).as_nanos() == 0
        {
            return Err(src.error_at_key("framework.period_s", "is shorter than a nanosecond"));
        }
        Ok(())
    }
}

/// A whole module configuration file, typed by the module's parameters.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ModuleConfigFile<P> {
    /// Framework keys.
    #[serde(default)]
    pub framework: FrameworkKeys,
    /// The module's own parameters.
    #[serde(default)]
    pub params: P,
}

/// Where a module's configuration comes from.
#[derive(Clone, Debug)]
pub enum ConfigSource {
    /// A TOML file on disk (reloadable and savable).
    File(PathBuf),
    /// TOML text held in memory, with a name for error messages.
    Inline {
        /// Description used in error messages.
        origin: String,
        /// The TOML text.
        text: String,
        /// Where an error in the text really comes from, when the text was made from the files a
        /// user wrote (defaults with a scenario's table merged over them): an error found in the
        /// made text is moved to the user's file, line and key.
        relocate: Option<Relocate>,
    },
}

/// Moves an error found in generated configuration text to where the user wrote the key.
#[derive(Clone)]
pub struct Relocate(pub std::sync::Arc<dyn Fn(ConfigError) -> ConfigError + Send + Sync>);

impl std::fmt::Debug for Relocate {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Relocate(..)")
    }
}

impl ConfigSource {
    /// A file source.
    pub fn file(path: impl Into<PathBuf>) -> Self {
        ConfigSource::File(path.into())
    }
    /// An inline source.
    pub fn inline(origin: impl Into<String>, text: impl Into<String>) -> Self {
        ConfigSource::Inline { origin: origin.into(), text: text.into(), relocate: None }
    }
    /// An inline source made from other files, whose errors `relocate` moves back to them.
    pub fn inline_from(
        origin: impl Into<String>,
        text: impl Into<String>,
        relocate: impl Fn(ConfigError) -> ConfigError + Send + Sync + 'static,
    ) -> Self {
        ConfigSource::Inline {
            origin: origin.into(),
            text: text.into(),
            relocate: Some(Relocate(std::sync::Arc::new(relocate))),
        }
    }
    /// `e`, moved to where the user wrote the key when this source was made from other files.
    pub fn relocate(&self, e: ConfigError) -> ConfigError {
        match self {
            ConfigSource::Inline { relocate: Some(r), .. } => (r.0)(e),
            _ => e,
        }
    }
    /// Name for error messages.
    pub fn origin(&self) -> String {
        match self {
            ConfigSource::File(p) => p.display().to_string(),
            ConfigSource::Inline { origin, .. } => origin.clone(),
        }
    }
    /// The current text.
    pub fn read(&self) -> Result<String, ConfigError> {
        match self {
            ConfigSource::File(p) => read_file(p),
            ConfigSource::Inline { text, .. } => Ok(text.clone()),
        }
    }
    /// Parses and validates the configuration.
    pub fn load<P: DeserializeOwned + Default>(&self) -> Result<(ModuleConfigFile<P>, String), ConfigError> {
        let text = self.read()?;
        let origin = self.origin();
        let src = Source::new(&origin, &text);
        let cfg: ModuleConfigFile<P> = src.parse()?;
        cfg.framework.validate(&src)?;
        Ok((cfg, text))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Debug, Default, Deserialize, Serialize, PartialEq)]
    #[serde(deny_unknown_fields)]
    struct P {
        #[serde(default)]
        gain: f64,
        #[serde(default)]
        name: String,
    }

    fn load(text: &str) -> Result<ModuleConfigFile<P>, ConfigError> {
        ConfigSource::inline("m.toml", text).load::<P>().map(|(c, _)| c)
    }

    #[test]
    fn good_file_loads() {
        let c = load("[framework]\nperiod_s = 0.02\ncontext = { mode = \"dry-run\", purpose = \"debug\" }\n[params]\ngain = 2.5\n")
            .unwrap();
        assert_eq!(c.framework.schedule(), Schedule::Periodic(Duration::from_millis(20)));
        assert_eq!(c.framework.context, ExecContext::DRY_RUN_DEBUG);
        assert_eq!(c.params.gain, 2.5);
        assert_eq!(load("").unwrap().framework.schedule(), Schedule::Aperiodic);
    }

    #[test]
    fn unknown_key_names_file_line_and_key() {
        let e = load("[framework]\nperiod_s = 0.1\n\n[params]\ngian = 2.0\n").unwrap_err();
        assert_eq!((e.file.as_str(), e.line), ("m.toml", 5), "{e}");
        assert!(e.to_string().contains("gian"), "{e}");
        assert!(e.to_string().starts_with("m.toml:5:"), "{e}");
    }

    #[test]
    fn wrong_type_names_the_key() {
        let e = load("[params]\ngain = \"fast\"\n").unwrap_err();
        assert_eq!(e.line, 2, "{e}");
        assert_eq!(e.key.as_deref(), Some("params.gain"), "{e}");
    }

    #[test]
    fn bad_values_and_syntax_are_located() {
        let e = load("[framework]\n\nperiod_s = -1.0\n").unwrap_err();
        assert_eq!((e.line, e.key.as_deref()), (3, Some("framework.period_s")), "{e}");
        let e = load("[framework\nperiod_s = 1\n").unwrap_err();
        assert_eq!(e.line, 1, "{e}");
        let e = load("[framework]\ncontext = { mode = \"sim\", purpose = \"debug\" }\n").unwrap_err();
        assert_eq!(e.line, 2, "{e}");
        assert!(e.to_string().contains("sim"), "{e}");
    }

    #[test]
    fn missing_file_is_named() {
        let e = ConfigSource::file("/nonexistent/x.toml").load::<P>().unwrap_err();
        assert!(e.to_string().starts_with("/nonexistent/x.toml: cannot read file"), "{e}");
    }

    #[test]
    fn line_and_column_count_characters() {
        let s = Source::new("f", "a = 1\nbé = 2\n");
        assert_eq!(s.line_col(6), (2, 1));
        assert_eq!(s.line_col(s.text.find('=').unwrap()), (1, 3));
        assert_eq!(s.line_col(12), (2, 6));
    }
}
