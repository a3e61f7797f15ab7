"""Names every layer above may use without importing a learner (this module imports nothing)."""

PROXY_Q = "proxy_q"  # the family of the reward-free proxy-Q learners
EVALUATE = "evaluate"  # the recipe (and family) of a fixed policy that is scored, not trained
# the proxy-Q recipes: each is pe_rlhf.algorithms.proxy_q.recipe.main with recipes/<name>/config.yaml
PROXY_Q_RECIPES = ("pe_rlhf", "haco", "haim_drl", "pvp")
