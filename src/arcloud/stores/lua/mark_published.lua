-- Raise how far a map's change log was published (never lower it: two publishers may race).
-- KEYS[1]: the map's published-version STRING. ARGV[1]: the version published up to.
local current = tonumber(redis.call('GET', KEYS[1]) or '0')
if tonumber(ARGV[1]) > current then
  redis.call('SET', KEYS[1], ARGV[1])
end
return 1
