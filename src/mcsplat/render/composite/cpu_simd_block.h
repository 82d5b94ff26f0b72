
            vf dx = mx - ((float)block_x0[b] + lane_dx);
            vf dy = my - ((float)block_y0[b] + lane_dy);
            vf power = -0.5f * (ca * dx * dx + cc * dy * dy) - cb * dx * dy;
            vi in_range = (power <= 0.0f) & (power >= power_skip);

            if (!any_lane(in_range & ({{TAKING_PART}}))) continue;

            vf gauss = exp_lanes(select(in_range, power, (vf)0.0f));
            vf raw_alpha = opacity * gauss;
            vf alpha = select(raw_alpha < alpha_max, raw_alpha, (vf)alpha_max);
            vi passes = in_range & (alpha >= alpha_min);
