"""Recipes: OmegaConf YAML files naming components by registered name, validated up front."""

from mosiv_framework.recipes.load import (
    check_recipe,
    load_recipe,
    read_recipe_file,
    validate_recipe,
)
from mosiv_framework.recipes.schema import Recipe
from mosiv_framework.recipes.stiffness import check_stiffness

__all__ = [
    "Recipe",
    "check_recipe",
    "check_stiffness",
    "load_recipe",
    "read_recipe_file",
    "validate_recipe",
]
