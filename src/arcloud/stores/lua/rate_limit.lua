-- One token of a GCRA rate limit (a token bucket kept as one number: the theoretical arrival time).
-- KEYS[1] the bucket. ARGV[1] rate (tokens a second), ARGV[2] burst (tokens).
-- Returns "0" when allowed (spent), else the seconds until a token is (as a string: Lua numbers
-- become integers on the way out). Redis's clock, so every API process shares one.
local now_parts = redis.call('TIME')
local now = tonumber(now_parts[1]) + tonumber(now_parts[2]) / 1e6
local interval = 1 / tonumber(ARGV[1])
local tat = tonumber(redis.call('GET', KEYS[1]) or '0')
if tat < now then tat = now end
local new_tat = tat + interval
local allowed_at = new_tat - tonumber(ARGV[2]) * interval
if allowed_at > now then return tostring(allowed_at - now) end
redis.call('SET', KEYS[1], string.format('%.6f', new_tat), 'PX', math.ceil((new_tat - now) * 1000) + 1)
return '0'
