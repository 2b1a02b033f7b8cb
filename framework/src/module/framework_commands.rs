//! The commands the framework handles for every module (lifecycle, configuration, meta-states,
//! state and statistics queries, fault injection).

use super::cell::Cell;
use super::*;
use crate::config::{ConfigSource, ModuleConfigFile, Source};
use crate::events::{EventKind, Fault};
use crate::exec_context::ExecContext;
use crate::lifecycle::Lifecycle;
use crate::message::Outcome;
use crate::runtime::Core;
use crate::time::Time;
use serde::Deserialize;
use serde::de::DeserializeOwned;
use std::collections::BTreeMap;
use std::panic::{AssertUnwindSafe, catch_unwind};

impl<M: Module> Cell<M> {
    pub(super) fn state_json(&self) -> serde_json::Value {
        let meta: BTreeMap<_, _> = self
            .fsm
            .states
            .iter()
            .filter(|s| s.meta)
            .map(|s| (s.name.clone(), s.impls[s.active].0.clone()))
            .collect();
        serde_json::json!({
            "module": self.info.name,
            "kind": self.info.kind,
            "lifecycle": self.lifecycle,
            "state": self.fsm.states.get(self.fsm.current).map(|s| s.name.as_str()),
            "context": self.exec.to_string(),
            "isolated": self.isolated,
            "meta_states": meta,
            "commands": self.commands.keys().collect::<Vec<_>>(),
        })
    }

    pub(super) fn framework_command(
        &mut self,
        core: &Core,
        now: Time,
        name: &str,
        args: serde_json::Value,
    ) -> Outcome {
        #[derive(Deserialize)]
        #[serde(deny_unknown_fields)]
        struct To {
            to: Lifecycle,
        }
        #[derive(Deserialize)]
        #[serde(deny_unknown_fields)]
        struct Meta {
            state: String,
            implementation: String,
        }
        #[derive(Deserialize)]
        #[serde(deny_unknown_fields)]
        struct SetContext {
            context: ExecContext,
        }
        #[derive(Deserialize)]
        #[serde(deny_unknown_fields)]
        struct SetParam {
            key: String,
            value: serde_json::Value,
        }
        #[derive(Deserialize)]
        #[serde(deny_unknown_fields)]
        struct Inject {
            kind: InjectedFault,
        }
        #[derive(Deserialize, Default)]
        #[serde(deny_unknown_fields)]
        struct Save {
            #[serde(default)]
            path: Option<std::path::PathBuf>,
        }
        fn parse<T: DeserializeOwned>(name: &str, args: serde_json::Value) -> Result<T, Outcome> {
            serde_json::from_value(args)
                .map_err(|e| Outcome::reject(format!("bad arguments for '{name}': {e}")))
        }
        let in_config = |this: &Self| {
            if this.lifecycle == Lifecycle::Config {
                Ok(())
            } else {
                Err(Outcome::reject(format!(
                    "'{name}' is allowed only in Config; module '{}' is in {}",
                    this.info.name, this.lifecycle
                )))
            }
        };
        let r: Result<Outcome, Outcome> = (|| match name {
            "ping" => Ok(Outcome::done()),
            "inject_fault" => {
                let Inject { kind } = parse(name, args)?;
                if self.isolated || self.lifecycle != Lifecycle::Run {
                    return Err(Outcome::reject(format!(
                        "module '{}' is not running ({}); nothing to inject into",
                        self.info.name, self.lifecycle
                    )));
                }
                self.injected = Some(kind);
                Ok(Outcome::Completed(serde_json::json!({ "injected": kind })))
            }
            "get_state" => Ok(Outcome::Completed(self.state_json())),
            "get_stats" => Ok(Outcome::Completed(serde_json::to_value(&self.stats).unwrap_or_default())),
            "lifecycle" => {
                let To { to } = parse(name, args)?;
                self.change_lifecycle(core, now, to)
            }
            "set_meta" => {
                let Meta { state, implementation } = parse(name, args)?;
                if self.isolated {
                    return Err(Outcome::reject(format!("module '{}' is isolated in Safe", self.info.name)));
                }
                let i = *self.fsm.index.get(&state).ok_or_else(|| {
                    Outcome::reject(format!("module '{}' has no state '{state}'", self.info.name))
                })?;
                let st = &mut self.fsm.states[i];
                if !st.meta {
                    return Err(Outcome::reject(format!("state '{state}' is not a meta-state")));
                }
                let k = st.impls.iter().position(|(n, _)| *n == implementation).ok_or_else(|| {
                    Outcome::reject(format!(
                        "meta-state '{state}' has no implementation '{implementation}' (it has: {})",
                        st.impls.iter().map(|(n, _)| n.as_str()).collect::<Vec<_>>().join(", ")
                    ))
                })?;
                st.active = k;
                core.status(self.info.id).set_meta(&state, &implementation);
                core.events.raise(
                    now,
                    EventKind::MetaStateSwitched { module: self.info.name.clone(), state, implementation },
                );
                Ok(Outcome::done())
            }
            "set_context" => {
                let SetContext { context } = parse(name, args)?;
                if !self.context_switchable {
                    return Err(Outcome::reject(format!(
                        "module '{}' does not allow its execution context to change at runtime",
                        self.info.name
                    )));
                }
                self.exec = context;
                core.status(self.info.id).set_context(context);
                Ok(Outcome::done())
            }
            "set_param" => {
                in_config(self)?;
                let SetParam { key, value } = parse(name, args)?;
                let mut doc: toml::Table = toml::from_str(&self.params_text)
                    .map_err(|e| Outcome::fail(format!("current configuration unreadable: {e}")))?;
                let tv: toml::Value = serde_json::from_value(value)
                    .map_err(|e| Outcome::reject(format!("value not representable in TOML: {e}")))?;
                let mut table = &mut doc;
                let parts: Vec<&str> = key.split('.').collect();
                for p in &parts[..parts.len() - 1] {
                    table = table
                        .entry(p.to_string())
                        .or_insert_with(|| toml::Value::Table(Default::default()))
                        .as_table_mut()
                        .ok_or_else(|| Outcome::reject(format!("'{p}' in '{key}' is not a table")))?;
                }
                table.insert(parts[parts.len() - 1].to_string(), tv);
                let text = toml::to_string(&doc).map_err(|e| Outcome::fail(e.to_string()))?;
                self.apply_config_text(&format!("<set_param {key} on module '{}'>", self.info.name), text)
            }
            "reload_config" => {
                in_config(self)?;
                let text = self.source.read().map_err(|e| Outcome::reject(e.to_string()))?;
                self.apply_config_text(&self.source.origin(), text)
            }
            "save_config" => {
                in_config(self)?;
                let Save { path } = if args.is_null() { Save::default() } else { parse(name, args)? };
                let path = match (path, &self.source) {
                    (Some(p), _) => p,
                    (None, ConfigSource::File(p)) => p.clone(),
                    (None, ConfigSource::Inline { .. }) => {
                        return Err(Outcome::reject("configuration is inline; give a path to save to"));
                    }
                };
                std::fs::write(&path, &self.params_text)
                    .map_err(|e| Outcome::fail(format!("cannot write {}: {e}", path.display())))?;
                Ok(Outcome::Completed(serde_json::json!({ "path": path })))
            }
            _ => Err(Outcome::reject(format!("unknown framework command '{name}'"))),
        })();
        r.unwrap_or_else(|o| o)
    }

    /// Parses, validates and applies a new configuration text (Config state only).
    pub(super) fn apply_config_text(&mut self, origin: &str, text: String) -> Result<Outcome, Outcome> {
        let src = Source::new(origin, &text);
        let cfg: ModuleConfigFile<M::Params> = src.parse().map_err(|e| Outcome::reject(e.to_string()))?;
        cfg.framework.validate(&src).map_err(|e| Outcome::reject(e.to_string()))?;
        self.module.configure(&cfg.params).map_err(|e| {
            Outcome::reject(format!("parameters rejected by module '{}': {e}", self.info.name))
        })?;
        self.exec = cfg.framework.context;
        self.keys = cfg.framework;
        self.params_text = text;
        Ok(Outcome::done())
    }

    pub(super) fn change_lifecycle(
        &mut self,
        core: &Core,
        now: Time,
        to: Lifecycle,
    ) -> Result<Outcome, Outcome> {
        let from = self.lifecycle;
        from.check_transition(to)
            .map_err(|e| Outcome::reject(format!("module '{}': {e}", self.info.name)))?;
        let mut ctx =
            Self::ctx(core, &self.info, &self.fsm, &mut self.ledger, now, self.exec, self.lifecycle);
        let module = &mut self.module;
        let r = catch_unwind(AssertUnwindSafe(|| module.on_transition(&mut ctx, from, to)));
        drop(ctx);
        match r {
            Ok(Err(reason)) if to != Lifecycle::Safe => {
                return Err(Outcome::reject(format!(
                    "module '{}' refused {from} -> {to}: {reason}",
                    self.info.name
                )));
            }
            Err(p) => {
                let text = panic_text(&*p);
                self.isolate(core, now, Fault::Panic(text.clone()));
                return Err(Outcome::fail(format!("transition hook panicked: {text}")));
            }
            _ => {}
        }
        self.lifecycle = to;
        if to == Lifecycle::Safe && from != Lifecycle::Safe {
            self.make_safe(core, now, "commanded");
            // As after an isolation: the module gives its devices back (it takes them again in Run).
            core.resources.release_all_of(self.info.id);
        }
        if from == Lifecycle::Safe {
            self.isolated = false;
            self.consecutive_overruns = 0;
            core.status(self.info.id).set_isolated(false);
        }
        core.status(self.info.id).set_lifecycle(to);
        core.events.raise(now, EventKind::ModuleLifecycle { module: self.info.name.clone(), from, to });
        Ok(Outcome::Completed(serde_json::json!({ "lifecycle": to })))
    }
}
