"""Recipes: OmegaConf YAML files naming components by registered name, validated up front."""

from mosiv_framework.recipes.load import load_recipe, read_recipe_file, validate_recipe
from mosiv_framework.recipes.schema import Recipe

__all__ = ["Recipe", "load_recipe", "read_recipe_file", "validate_recipe"]
