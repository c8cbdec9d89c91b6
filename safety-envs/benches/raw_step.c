/* The baseline for `benches/envs.rs`: the same agent steps as SafeDarkMujoco
 * (write two controls, then `physics_steps_per_action` calls of mj_step), in plain C on the
 * same compiled model, with nothing else around them. */
#include <mujoco/mujoco.h>

/* Runs `agent_steps` agent steps on (m, d); controls cycle through the
 * `n_actions` pairs in `actions`. Returns d->time so the work stays live. */
double raw_agent_steps(const mjModel* m, mjData* d, long agent_steps,
                       int physics_steps_per_action, const float* actions, long n_actions) {
  for (long t = 0; t < agent_steps; t++) {
    const float* a = actions + 2 * (t % n_actions);
    d->ctrl[0] = a[0];
    d->ctrl[1] = a[1];
    for (int k = 0; k < physics_steps_per_action; k++) {
      mj_step(m, d);
    }
  }
  return d->time;
}
