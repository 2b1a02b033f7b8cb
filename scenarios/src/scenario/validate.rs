//! What a scenario's types cannot check: positive and bounded durations and rates, phases that
//! exist, plans that can run, finite numbers everywhere.

use super::{FileText, QueueName, Scenario, locate};
use framework::config::{ConfigError, num};

/// Longest duration a scenario may name (a time limit, a timeout, a delay, an event's time), s:
/// far beyond any mission, and far from overflowing the clock's nanoseconds when a few add up.
pub const MAX_DURATION_S: f64 = 1e7;
/// Highest logging rate, Hz.
pub const MAX_LOG_HZ: f64 = 1000.0;
/// Shortest base period, s.
pub const MIN_BASE_PERIOD_S: f64 = 1e-6;

/// Checks values the types cannot.
pub(super) fn validate(
    s: &Scenario,
    files: &[FileText],
    overrides: &[(String, String)],
) -> Result<(), ConfigError> {
    let err = |key: &str, msg: String| {
        let parts: Vec<String> = key.split('.').map(String::from).collect();
        Err(locate(&parts, files, overrides, msg))
    };
    let positive = |key: &str, v: f64| {
        if v.is_finite() && v > 0.0 { Ok(()) } else { err(key, format!("must be positive, got {v}")) }
    };
    // Every duration: finite, >= 0 (or > 0 where zero cannot work), and bounded.
    let duration = |key: &str, v: f64, zero_ok: bool| {
        if !(v.is_finite() && (v > 0.0 || (zero_ok && v == 0.0))) {
            let want = if zero_ok { ">= 0" } else { "positive" };
            return err(key, format!("must be {want}, got {}", num(v)));
        }
        if v > MAX_DURATION_S {
            return err(
                key,
                format!("{} s is more than the {MAX_DURATION_S:.0e} s a scenario may name", num(v)),
            );
        }
        Ok(())
    };
    duration("run.time_limit_s", s.run.time_limit_s, false)?;
    duration("run.settle_s", s.run.settle_s, true)?;
    duration("run.observe_s", s.run.observe_s, true)?;
    for (i, p) in s.phases.iter().enumerate() {
        for (j, st) in p.steps.iter().enumerate() {
            duration(&format!("phase.{i}.steps.{j}.timeout_s"), st.timeout_s, false)?;
        }
        for (j, st) in p.recovery.iter().enumerate() {
            duration(&format!("phase.{i}.recovery.{j}.timeout_s"), st.timeout_s, false)?;
        }
        duration(&format!("phase.{i}.retry_delay_s"), p.retry_delay_s, true)?;
    }
    for (i, e) in s.events.iter().enumerate() {
        if let Some(t) = e.at_s {
            duration(&format!("event.{i}.at_s"), t, true)?;
        }
        duration(&format!("event.{i}.after_s"), e.after_s, true)?;
    }
    if let Some(m) = s.canister.as_ref().and_then(|c| c.motion.as_ref()) {
        duration("canister.motion.start_s", m.start_s, true)?;
        duration("canister.motion.duration_s", m.duration_s, true)?;
    }
    positive("run.base_period_s", s.run.base_period_s)?;
    if s.run.base_period_s < MIN_BASE_PERIOD_S || s.run.base_period_s > 1.0 {
        return err(
            "run.base_period_s",
            format!("must be in [{MIN_BASE_PERIOD_S}, 1] s, got {}", s.run.base_period_s),
        );
    }
    for (k, v) in [
        ("rover.known_sigma_m", s.rover.known_sigma_m),
        ("rover.known_sigma_deg", s.rover.known_sigma_deg),
        ("operator.survey_sigma[0]", s.operator.survey_sigma[0]),
        ("operator.survey_sigma[1]", s.operator.survey_sigma[1]),
    ] {
        if !(v >= 0.0 && v.is_finite()) {
            return err(k, format!("must be >= 0, got {v}"));
        }
    }
    if let Some(f) = s.world.friction
        && !(f.is_finite() && f >= 0.0)
    {
        return err("world.friction", format!("must be >= 0, got {f}"));
    }
    for name in s.modules.keys() {
        if !crate::module_names::MODULES.contains(&name.as_str()) {
            let modules = crate::module_names::MODULES.join(", ");
            return err(
                &format!("modules.{name}"),
                format!("no module '{name}' in this system (it has: {modules})"),
            );
        }
    }
    let mut names = std::collections::HashSet::new();
    for (i, p) in s.phases.iter().enumerate() {
        if !names.insert(p.name.as_str()) {
            return err(&format!("phase.{i}.name"), format!("phase '{}' appears twice", p.name));
        }
    }
    if let Some(req) = &s.criteria.required_phases {
        for (i, r) in req.iter().enumerate() {
            if !names.contains(r.as_str()) {
                return err(&format!("criteria.required_phases.{i}"), format!("no phase named '{r}'"));
            }
        }
    }
    for (i, p) in s.phases.iter().enumerate() {
        for (j, a) in p.after.iter().flatten().enumerate() {
            if !names.contains(a.as_str()) {
                return err(&format!("phase.{i}.after.{j}"), format!("no phase named '{a}'"));
            }
        }
        for (k, list) in [("steps", &p.steps), ("recovery", &p.recovery)] {
            if let Some(j) = list.iter().position(|st| st.queue == QueueName::Debug) {
                return err(
                    &format!("phase.{i}.{k}.{j}.queue"),
                    "the plan's commands go on the nominal or emergency queue; debug commands are [[event]]s, sent through the Debugger".into(),
                );
            }
        }
    }
    if let Err(e) = s.plan().dependencies() {
        return err("phase", e.replace("activity", "phase"));
    }
    for (i, e) in s.events.iter().enumerate() {
        let triggers = [
            e.at_s.is_some(),
            e.phase.is_some(),
            e.phase_end.is_some(),
            e.near.is_some(),
            e.module_state.is_some(),
        ];
        if e.at_s.is_some() && e.after_s != 0.0 {
            return err(
                &format!("event.{i}.after_s"),
                "applies to a condition; with at_s give the time itself".into(),
            );
        }
        if let Some(m) = &e.module_state {
            // Lifecycle states are capitalised, a module's own states are not: a near miss of a
            // lifecycle name would never fire.
            if let Some(l) =
                framework::Lifecycle::ALL.iter().find(|l| l.name().eq_ignore_ascii_case(&m.state))
                && l.name() != m.state
            {
                return err(
                    &format!("event.{i}.module_state.state"),
                    format!("'{}' is not a state; the lifecycle state is '{}'", m.state, l.name()),
                );
            }
        }
        if triggers.iter().filter(|t| **t).count() != 1 {
            return err(
                &format!("event.{i}"),
                "give one of at_s, phase, phase_end, near or module_state (with after_s)".into(),
            );
        }
        for (k, p) in [("phase", &e.phase), ("phase_end", &e.phase_end)] {
            if let Some(p) = p
                && !names.contains(p.as_str())
            {
                return err(&format!("event.{i}.{k}"), format!("no phase named '{p}'"));
            }
        }
        if let Some(n) = &e.near
            && !(n.within_m > 0.0 && n.within_m <= 1e4)
        {
            return err(
                &format!("event.{i}.near.within_m"),
                format!("must be in (0, 1e4] m, got {}", num(n.within_m)),
            );
        }
        if let Some(m) = &e.module_state
            && m.module != "system"
            && !crate::module_names::MODULES.contains(&m.module.as_str())
        {
            return err(
                &format!("event.{i}.module_state.module"),
                format!(
                    "no module '{}' (it has: system, {})",
                    m.module,
                    crate::module_names::MODULES.join(", ")
                ),
            );
        }
    }
    let l = &s.logging;
    for (k, v) in [
        ("logging.truth_hz", l.truth_hz),
        ("logging.slots_hz", l.slots_hz),
        ("logging.images_hz", l.images_hz),
        ("logging.maps_hz", l.maps_hz),
        ("logging.stats_hz", l.stats_hz),
    ] {
        if !(v.is_finite() && (0.0..=MAX_LOG_HZ).contains(&v)) {
            return err(
                k,
                format!("must be in [0, {MAX_LOG_HZ}] Hz (0 turns the stream off), got {}", num(v)),
            );
        }
    }
    if l.image_downsample == 0 {
        return err("logging.image_downsample", "must be at least 1".into());
    }
    Ok(())
}
