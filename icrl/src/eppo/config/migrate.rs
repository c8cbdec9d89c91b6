//! The flat form of configs written before the sections, the retired
//! settings, and `--set`s by a setting's name: one table of each setting's
//! section ([`EppoConfig::SECTIONS`]) serves all three.

use super::{EppoConfig, EppoError};

/// Settings tried by a ladder, measured as not helping, and removed with
/// their code: each with the value at which it did nothing, or that the code
/// now holds fixed (`None`: it acted only through another retired setting),
/// and the last commit that had it (`git checkout` it to rerun such a config). A config written before the
/// removal still loads where it holds one at that value; one that used it is
/// refused by name.
pub const RETIRED: [(&str, Option<&str>, &str); 25] = [
    // The PID Lagrangian (results/eppo_darkroom_budget, issue 18).
    ("lambda_kp", Some("0.0"), PID_AND_LATE_RATE),
    ("lambda_kd", Some("0.0"), PID_AND_LATE_RATE),
    ("lambda_smoothing", None, PID_AND_LATE_RATE),
    // The late-episode over-budget rate as the multiplier's signal (lr1, lr2).
    (
        "violation_signal",
        Some("\"worst_excess\""),
        PID_AND_LATE_RATE,
    ),
    ("lambda_target_rate", None, PID_AND_LATE_RATE),
    // The actor's loss reshaped (results/eppo_ladder r3 and the Point ladder):
    // its encoder detached, and AMAGO's filtered behaviour cloning.
    ("actor_detach_encoder", Some("false"), ACTOR_AND_ANNEAL),
    ("bc_coef", Some("0.0"), ACTOR_AND_ANNEAL),
    // The novelty bonus annealed to 0 over training (Point ps6).
    ("novelty_anneal_updates", Some("0"), ACTOR_AND_ANNEAL),
    // A head reading where earlier costs were paid off the encoding (Point
    // pe2: it cost the return trip).
    ("hazard_recall_coef", Some("0.0"), HAZARD_RECALL),
    // The novelty bonus rising with the episode index (dn1, Point ps7) and
    // scaled by the distance from the episode's start (Car cd1, cd2).
    ("novelty_rise", Some("0.0"), NOVELTY_SHAPES_AND_RAMP),
    (
        "novelty_distance_scale",
        Some("0.0"),
        NOVELTY_SHAPES_AND_RAMP,
    ),
    // The over-budget price moved linearly rather than in steps (dw2u).
    (
        "over_budget_price_ramp",
        Some("false"),
        NOVELTY_SHAPES_AND_RAMP,
    ),
    // Behaviour noise capped once the trajectory has found its goal
    // (results/eppo_darkroom_budget ls1; a ceiling of 1 caps nothing).
    ("eps_after_success", Some("1.0"), SEARCH_AND_PRICE_VARIANTS),
    // A share of the first episodes scripted to the goal, the rest searching
    // (Point rb4-rb7, Car cb2 and cs9: the car repeated its first episode).
    ("scripted_share", Some("1.0"), SEARCH_AND_PRICE_VARIANTS),
    // Observations standardised by a random policy's statistics (Point rn1),
    // and each step's index within its episode in the token (built for
    // Point's return trip, never run by a ladder).
    (
        "standardise_observations",
        Some("false"),
        SEARCH_AND_PRICE_VARIANTS,
    ),
    (
        "episode_positions",
        Some("false"),
        SEARCH_AND_PRICE_VARIANTS,
    ),
    // The novelty critics charged the over-budget price (Point pc5, pc7) and
    // paid past the first success (Point ps9, ps10, Car cs7).
    (
        "novelty_pays_price",
        Some("false"),
        SEARCH_AND_PRICE_VARIANTS,
    ),
    (
        "novelty_through_success",
        Some("false"),
        SEARCH_AND_PRICE_VARIANTS,
    ),
    // Saute's unsafe reward other than its default -0.1, now fixed
    // (results/eppo_darkroom_budget sa3-sa5).
    (
        "saute_unsafe_reward",
        Some("-0.1"),
        SEARCH_AND_PRICE_VARIANTS,
    ),
    // The termination sparing the novelty critics' value (Point pt5), and the
    // price or termination narrowed to repeated costs (Point pc7, pt4).
    (
        "termination_spares_search",
        Some("false"),
        SEARCH_AND_PRICE_VARIANTS,
    ),
    ("repeat_cost_radius", Some("0.0"), SEARCH_AND_PRICE_VARIANTS),
    // A reward at the step whose overspending ends the value under
    // penalty = "terminate" (Point pt2: -1 did not help pt1's 0).
    ("termination_reward", Some("0.0"), TERMINATION_REWARD),
    // The task's hazard map in the observation, hidden in a rising share of
    // trajectories (Point pe3: the agent that saw the map crossed it too).
    ("hazards_in_observation", Some("false"), HAZARD_MAP),
    ("hazard_hidden_share", Some("0.0"), HAZARD_MAP),
    ("hazard_hidden_ramp", None, HAZARD_MAP),
];

const PID_AND_LATE_RATE: &str = "b1f1bdb663c9833aefcfffa79f077dcd3d455b0b";
const ACTOR_AND_ANNEAL: &str = "db40554803feeb6dadd0adc8842796b03fa193c4";
const HAZARD_RECALL: &str = "8a5cee241507924037a24029831611b616eec709";
const NOVELTY_SHAPES_AND_RAMP: &str = "1096eed9892161592b2878611d3cef89371e88d3";
const SEARCH_AND_PRICE_VARIANTS: &str = "9441cf84b763fafdac321359355efe089241a33d";
const TERMINATION_REWARD: &str = "a90f1fd2ff672362480194053975e382ab8de2f8";
const HAZARD_MAP: &str = "407d3a293586c689f7a4f88e4a4378db462226a7";

/// Drops the [`RETIRED`] settings of `table`, flat or in a section, that
/// hold their inert value; refuses one that does not, naming it.
pub fn drop_retired(table: &mut toml::Table) -> Result<(), String> {
    drop_retired_from(table)?;
    for (section, _) in EppoConfig::SECTIONS {
        if let Some(toml::Value::Table(settings)) = table.get_mut(section) {
            drop_retired_from(settings)?;
        }
    }
    Ok(())
}

/// [`drop_retired`] on one level of a table.
fn drop_retired_from(table: &mut toml::Table) -> Result<(), String> {
    for (key, inert, commit) in RETIRED {
        let Some(value) = table.get(key) else {
            continue;
        };
        let inert = inert.map(|text| {
            toml::from_str::<toml::Table>(&format!("v = {text}"))
                .expect("RETIRED holds TOML values")["v"]
                .clone()
        });
        let number = |v: &toml::Value| v.as_float().or(v.as_integer().map(|i| i as f64));
        let did_nothing = match &inert {
            None => true,
            Some(inert) => match (number(value), number(inert)) {
                (Some(a), Some(b)) => a == b,
                _ => value == inert,
            },
        };
        if !did_nothing {
            return Err(format!(
                "{key} = {value} is a setting removed after its runs showed it did not help \
                 (the ladders under results/ record them): drop it to train without it, or check \
                 out commit {commit}, the last that had it, to rerun this config as it was"
            ));
        }
        table.remove(key);
    }
    Ok(())
}

impl EppoConfig {
    /// Every setting by its section, in one place: a flat config (every
    /// config written before the sections) is moved into them by
    /// [`EppoConfig::migrate`], and `--set NAME=VALUE` finds NAME's section
    /// here ([`EppoConfig::apply_sets`]). Names are unique across sections.
    /// The transformer's own settings are `model.NAME` in both forms; the
    /// older names `saute_cost_price` and `novelty_within_budget`, which
    /// their fields still read, move with them.
    pub const SECTIONS: [(&'static str, &'static [&'static str]); 9] = [
        (
            "run",
            &[
                "seed",
                "device",
                "torch_threads",
                "env_threads",
                "overlap",
                "learner_threads",
                "checkpoint_every",
                "keep_checkpoints",
                "keep_every",
            ],
        ),
        (
            "tasks",
            &[
                "max_episode_steps",
                "k_min",
                "k_max",
                "ctg_min",
                "ctg_max",
                "n_envs",
                "physics_steps_per_action",
                "task_pool",
            ],
        ),
        ("model", &["encoder_hidden", "head_hidden", "n_critics"]),
        (
            "optimisation",
            &[
                "lr",
                "beta1",
                "beta2",
                "adam_eps",
                "grad_clip",
                "critic_weight",
                "batch_size",
                "total_updates",
                "updates_per_round",
                "learning_starts",
                "replay_ratio",
            ],
        ),
        (
            "targets",
            &[
                "gamma",
                "bootstrap_across_episodes",
                "tau",
                "n_step",
                "reward_scale",
                "replay_capacity",
            ],
        ),
        (
            "constraint",
            &[
                "penalty",
                "lambda_lr",
                "lambda_max",
                "lambda_init",
                "per_episode_multipliers",
                "lambda_warmup_updates",
                "constraint_after_revisit",
                "constraint_revisit_rounds",
                "over_budget_cost_price",
                "saute_cost_price",
                "over_budget_price_schedule",
            ],
        ),
        (
            "exploration",
            &[
                "eps_start",
                "eps_end",
                "eps_decay_steps",
                "eps_last_start",
                "eps_last_end",
                "eps_random_scale",
                "entropy_coef",
                "target_entropy",
                "entropy_coef_lr",
            ],
        ),
        (
            "novelty",
            &[
                "novelty_bonus",
                "novelty_cell",
                "novelty_critic",
                "novelty_budget",
                "novelty_within_budget",
            ],
        ),
        (
            "goal",
            &[
                "relabel_prob",
                "dense_reward_coef",
                "dense_reward_after_goal",
                "goal_recall_coef",
                "goal_in_observation",
                "goal_hidden_share",
                "goal_hidden_ramp",
                "scripted_first_episode",
            ],
        ),
    ];

    /// The section that holds setting `name` ([`EppoConfig::SECTIONS`]).
    pub fn section_of(name: &str) -> Option<&'static str> {
        Self::SECTIONS
            .iter()
            .find(|(_, names)| names.contains(&name))
            .map(|(section, _)| *section)
    }

    /// Moves each setting of a flat config into its section (the sectioned
    /// form is left as it is; a mix of both is read too). Refuses, by name,
    /// a setting given twice (flat and in its section) or in a section not
    /// its own. Names of no section (retired or unknown) stay where they
    /// are, for [`EppoConfig::from_table`] to drop or refuse.
    pub fn migrate(table: &mut toml::Table) -> Result<(), String> {
        for (section, _) in Self::SECTIONS {
            let Some(settings) = table.get(section).and_then(toml::Value::as_table) else {
                continue;
            };
            if let Some((key, own)) = settings
                .keys()
                .find_map(|key| Some((key, Self::section_of(key)?)).filter(|(_, s)| s != &section))
            {
                return Err(format!(
                    "[{section}] holds {key}, a setting of [{own}]: move it there"
                ));
            }
        }
        let flat: Vec<String> = table
            .keys()
            .filter(|key| Self::section_of(key).is_some())
            .cloned()
            .collect();
        for key in flat {
            let section = Self::section_of(&key).expect("filtered on it");
            let value = table.remove(&key).expect("a key of the table");
            let entry = table
                .entry(section)
                .or_insert_with(|| toml::Value::Table(toml::Table::new()));
            let Some(settings) = entry.as_table_mut() else {
                return Err(format!(
                    "{section} = {entry} must be a table of settings ([{section}])"
                ));
            };
            if settings.contains_key(&key) {
                return Err(format!(
                    "{key} is set twice, at the top (the flat form of older configs) and in \
                     [{section}]: keep one"
                ));
            }
            settings.insert(key, value);
        }
        Ok(())
    }

    /// `--set NAME=VALUE`s on an EPPO config's table, flat or sectioned:
    /// the table moves into sections ([`EppoConfig::migrate`]), then a NAME
    /// of [`EppoConfig::SECTIONS`] applies in its section (`lambda_max=1` as
    /// `constraint.lambda_max=1`), a dotted one (`model.n_layers=2`,
    /// `constraint.lambda_max=1`) as it is, and any other at the top, where
    /// [`EppoConfig::from_table`] refuses it by name.
    pub fn apply_sets(table: &mut toml::Table, sets: &[String]) -> Result<(), EppoError> {
        Self::migrate(table).map_err(EppoError::Config)?;
        let mut sets = sets.to_vec();
        for set in &mut sets {
            let Some((key, value)) = set.split_once('=') else {
                continue; // refused by apply_overrides, as given
            };
            let key = key.trim();
            let section = match (Self::section_of(key), key.split_once('.')) {
                (Some(section), _) => {
                    *set = format!("{section}.{key}={value}");
                    section
                }
                (None, Some((section, _))) => section,
                (None, None) => continue,
            };
            // The optional sections may be absent.
            if Self::SECTIONS.iter().any(|(s, _)| *s == section) {
                table
                    .entry(section)
                    .or_insert_with(|| toml::Value::Table(toml::Table::new()));
            }
        }
        crate::presets::apply_overrides(table, &sets).map_err(|e| EppoError::Config(e.to_string()))
    }

    /// The value of setting `name` in a config's table, flat or sectioned
    /// (any other table: its own `name`).
    pub fn setting<'a>(table: &'a toml::Table, name: &str) -> Option<&'a toml::Value> {
        table
            .get(name)
            .or_else(|| table.get(Self::section_of(name)?)?.get(name))
    }

    /// A setting's name as `--set` and messages give it: `lambda_max` for
    /// `constraint.lambda_max`; the transformer's `model.d_model`, and any
    /// other name, as it is.
    pub fn flat_name(dotted: &str) -> &str {
        match dotted.split_once('.') {
            Some((section, name)) if Self::section_of(name) == Some(section) => name,
            _ => dotted,
        }
    }

    /// A config from a TOML table (a preset with its `--set`s, or a run's
    /// `config.toml`), in sections or in the flat form written before them
    /// ([`EppoConfig::migrate`]), and before or after the [`RETIRED`]
    /// settings went. An unknown name is refused with the valid ones.
    /// `name` says where the table came from, in errors.
    pub fn from_table(name: &str, mut table: toml::Table) -> Result<Self, EppoError> {
        let refuse = |e: String| EppoError::Config(format!("{name}: {e}"));
        drop_retired(&mut table).map_err(refuse)?;
        Self::migrate(&mut table).map_err(refuse)?;
        if let Some(key) = table
            .keys()
            .find(|key| Self::SECTIONS.iter().all(|(section, _)| section != key))
        {
            let known: Vec<String> = Self::SECTIONS
                .iter()
                .map(|(section, names)| format!("[{section}] {}", names.join(", ")))
                .collect();
            return Err(refuse(format!(
                "unknown setting {key:?}; the settings, flat or in their sections, are: {} \
                 (and the transformer's in [model])",
                known.join("; ")
            )));
        }
        crate::presets::resolve::<EppoConfig>(name, table)
            .map_err(|e| EppoError::Config(e.to_string()))
    }
}
